// Cancel / Retry / Delete buttons for a job or a scene, as its state allows.
import { api } from "../api.js";
import { h, showError } from "../dom.js";
import { isActive } from "../format.js";
import { paths, routes } from "../urls.js";

export function actions(kind, id, state, onDeleted) {
  const act = (label, method, path, after) => h("button", { class: "secondary", id: `${label.toLowerCase()}-${id}`, onclick: async () => {
    try { after(await api(path, { method })); } catch (error) { showError(error.message); }
  } }, label);
  const base = kind === "scene" ? paths.scene(id) : paths.job(id);
  const route = kind === "scene" ? routes.scene : routes.job;
  return h("p", {},
    isActive(state) ? act("Cancel", "POST", `${base}/cancel`, () => {}) : null, " ",
    ["failed", "cancelled"].includes(state) ? act("Retry", "POST", `${base}/retry`, async (r) => {
      location.hash = route((await r.json()).id);
    }) : null, " ",
    act("Delete", "DELETE", base, onDeleted));
}
