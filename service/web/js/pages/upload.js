// #/new : drop photos (or a zip), match files and a calibration; start a reconstruction or a whole scene.
import { api } from "../api.js";
import { h, showError } from "../dom.js";
import { addToChoice, choiceSummary, emptyChoice } from "../upload_files.js";
import { paths, routes } from "../urls.js";

export function uploadPage(main) {
  const chosen = emptyChoice();
  const lists = h("div");
  const picker = h("input", { type: "file", multiple: true, hidden: true, id: "files",
    onchange: () => addFiles(picker.files) });
  const drop = h("div", { class: "drop", id: "drop", onclick: () => picker.click() },
    "Drop photos here (PNG/JPEG or one .zip of them), with optional matching<i>.txt files and calibration.txt — or click to choose");
  const addFiles = (files) => {
    for (const name of addToChoice(chosen, files)) {
      showError(`${name}: not a photo (PNG/JPEG), a zip, a matching<i>.txt or a calibration .txt; left out`);
    }
    lists.replaceChildren(h("p", {}, choiceSummary(chosen)),
      h("ul", { class: "files" }, chosen.images.map((f) => h("li", {}, f.name))));
  };
  drop.addEventListener("dragover", (e) => { e.preventDefault(); drop.classList.add("over"); });
  drop.addEventListener("dragleave", () => drop.classList.remove("over"));
  drop.addEventListener("drop", (e) => { e.preventDefault(); drop.classList.remove("over"); addFiles(e.dataTransfer.files); });

  const field = (label, input) => h("label", {}, label, input);
  const what = h("select", { name: "what", id: "what" },
    h("option", { value: "scene" }, "Scene: reconstruction → NeRF → novel views"),
    h("option", { value: "reconstruction" }, "Reconstruction only"));
  const K = h("input", { name: "K", size: 36, placeholder: "fx 0 cx 0 fy cy 0 0 1 (if no calibration file)" });
  const features = h("select", { name: "features" }, ["auto", "matches", "sift"].map((v) => h("option", { value: v }, v)));
  const ransac = h("input", { name: "ransac_threshold_px", type: "number", step: "any", min: 0, placeholder: "default" });
  const ba = h("input", { name: "ba_max_iterations", type: "number", min: 1, placeholder: "default" });
  const model = h("select", { name: "model" }, ["fast", "vanilla"].map((v) => h("option", { value: v }, v)));
  const minutes = h("input", { name: "minutes", type: "number", step: "any", min: 0, placeholder: "default" });
  const steps = h("input", { name: "steps", type: "number", min: 1, placeholder: "or steps" });
  const frames = h("input", { name: "orbit_frames", type: "number", min: 1, placeholder: "36" });
  const trainSide = h("input", { name: "train_max_side", type: "number", min: 8, placeholder: "for the budget" });
  const nerfRow = h("div", { class: "row" }, field("NeRF model", model), field("Training minutes", minutes),
    field("or steps", steps), field("Video frames", frames), field("Training photo size (px)", trainSide));
  what.addEventListener("change", () => { nerfRow.hidden = what.value !== "scene"; });
  const submit = h("button", { type: "submit", id: "submit" }, "Start");

  const form = h("form", { id: "upload", onsubmit: async (event) => {
    event.preventDefault();
    const body = new FormData();
    chosen.images.forEach((f) => body.append("images", f, f.name));
    chosen.matches.forEach((f) => body.append("matches", f, f.name));
    if (chosen.calibration) body.append("calibration", chosen.calibration, chosen.calibration.name);
    if (chosen.zip) body.append("photos_zip", chosen.zip, chosen.zip.name);
    const set = (name, value) => { if (value !== "" && value !== null) body.append(name, value); };
    set("K", K.value.trim()); set("features", features.value);
    set("ransac_threshold_px", ransac.value); set("ba_max_iterations", ba.value);
    const scene = what.value === "scene";
    if (scene) {
      set("model", model.value); set("minutes", minutes.value); set("steps", steps.value); set("orbit_frames", frames.value);
      set("train_max_side", trainSide.value);
    }
    if (!scene && chosen.zip) { showError("a zip of photos starts a scene; for a reconstruction drop the photos themselves"); return; }
    submit.disabled = true;
    try {
      const created = await (await api(scene ? paths.createScene : paths.createReconstruction, { method: "POST", body })).json();
      showError("");
      location.hash = scene ? routes.scene(created.id) : routes.job(created.id);
    } catch (error) {
      showError(error.message);
    } finally {
      submit.disabled = false;
    }
  } },
  drop, picker, lists,
  h("div", { class: "row" }, field("Start", what), field("K", K), field("Features", features),
    field("RANSAC threshold (px)", ransac), field("BA iterations", ba)),
  nerfRow, submit);
  main.append(h("h1", {}, "New upload"), form);
}
