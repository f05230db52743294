// DOM helpers shared by the pages: element building, the error banner, progress bars, polling and guarded
// sections. Nothing here sets inline style or event-handler attributes (the page runs under a strict CSP).
import { barWidth, percent } from "./format.js";

export const POLL_MS = 1500;

export function showError(message) {
  const box = document.getElementById("error");
  box.textContent = message;
  box.hidden = !message;
}

// h("a", {href, onclick: f, dataset: {...}}, ...children): `on*` become listeners, never attributes.
export function h(tag, attributes = {}, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attributes)) {
    if (key.startsWith("on")) node.addEventListener(key.slice(2), value);
    else if (key === "dataset") Object.assign(node.dataset, value);
    else if (value !== undefined && value !== null && value !== false) node.setAttribute(key, value);
  }
  node.append(...children.flat().filter((c) => c !== null && c !== undefined));
  return node;
}

export function progressBar(fraction) {
  const filled = h("span");
  filled.style.width = barWidth(fraction); // through the CSSOM: a style attribute would need 'unsafe-inline'
  return h("span", { class: "bar", title: percent(fraction) }, filled);
}

export const stateText = (state) => h("span", { class: `state-${state}` }, state);

// Runs `step` now and every POLL_MS until it returns false or the page closes; errors are shown, not fatal.
export function poll(page, step) {
  const tick = async () => {
    if (page.closed) return;
    let again = true;
    try {
      again = (await step()) !== false;
      showError("");
    } catch (error) {
      showError(error.message);
    }
    if (again && !page.closed) page.timers.push(setTimeout(tick, POLL_MS));
  };
  tick();
}

// Guard for one-shot loads inside a page: shows the error in place of the section.
export async function section(container, load) {
  try {
    await load();
  } catch (error) {
    container.replaceChildren(h("p", { class: "muted" }, error.message));
  }
}
