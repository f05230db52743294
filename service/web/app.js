// The sfmnerf web app: a hash-routed single page on the service's REST API (/v1), nothing else.
// Pages: #/ (scenes and jobs), #/new (upload), #/jobs/{id}, #/scenes/{id} (js/pages/). Every API error is
// shown as the service's `detail` message; an unexpected page error as one readable line, never a stack trace.
import { TOKEN_KEY } from "./js/api.js";
import { showError } from "./js/dom.js";
import { route } from "./js/router.js";

function setUpToken() {
  const input = document.getElementById("token");
  input.value = localStorage.getItem(TOKEN_KEY) || "";
  input.addEventListener("change", () => {
    if (input.value) localStorage.setItem(TOKEN_KEY, input.value);
    else localStorage.removeItem(TOKEN_KEY);
    route();
  });
}

window.addEventListener("error", (event) => showError(`Something went wrong in the page: ${event.message}`));
window.addEventListener("unhandledrejection", (event) => showError(`Something went wrong in the page: ${event.reason?.message || event.reason}`));
window.addEventListener("hashchange", route);
setUpToken();
route();
