// The hash router: each route change closes the current page (its timers and 3D views) and opens the next.
import { showError } from "./dom.js";
import { listPage } from "./pages/list.js";
import { jobPage } from "./pages/job.js";
import { scenePage } from "./pages/scene.js";
import { uploadPage } from "./pages/upload.js";
import { parseRoute } from "./urls.js";

let current = null;

export function route() {
  if (current) {
    current.closed = true;
    current.timers.forEach(clearTimeout);
    current.disposers.forEach((dispose) => dispose());
  }
  current = { closed: false, timers: [], disposers: [] };
  showError("");
  const main = document.getElementById("main");
  main.replaceChildren();
  const target = parseRoute(location.hash);
  if (target.page === "new") uploadPage(main);
  else if (target.page === "job") jobPage(main, current, target.id);
  else if (target.page === "scene") scenePage(main, current, target.id);
  else listPage(main, current);
}
