// #/jobs/{id} : one job, its state and actions; a NeRF's training panel; a reconstruction's model; the log.
import { getJson } from "../api.js";
import { h, poll, progressBar, stateText } from "../dom.js";
import { isActive, percent } from "../format.js";
import { actions } from "../panels/actions.js";
import { logPanel } from "../panels/log.js";
import { nerfPanel } from "../panels/nerf.js";
import { reconstructionPanel } from "../panels/reconstruction.js";
import { paths, routes } from "../urls.js";

export function jobPage(main, page, jobId) {
  const head = h("div"), body = h("div");
  main.append(h("h1", {}, `Job ${jobId.slice(0, 8)}`), head, body);
  let shown = false;
  poll(page, async () => {
    const job = await getJson(paths.job(jobId));
    head.replaceChildren(h("div", { class: "panel", id: "job", dataset: { state: job.state, kind: job.kind } },
      h("p", {}, `${job.kind}: `, stateText(job.state), ` — ${job.stage || ""} `, progressBar(job.progress),
        ` ${percent(job.progress)}`),
      job.error ? h("p", { class: "error" }, job.error) : null,
      job.source_job_id ? h("p", {}, "Source: ", h("a", { href: routes.job(job.source_job_id) }, job.source_job_id)) : null,
      actions("job", jobId, job.state, () => { location.hash = routes.list; })));
    if (!shown) {
      shown = true;
      if (job.kind === "nerf") body.append(nerfPanel(page, jobId));
      body.append(logPanel(page, jobId));
    }
    if (job.kind === "reconstruction" && job.state === "succeeded" && !body.querySelector(".view3d")) {
      body.prepend(reconstructionPanel(page, jobId));
    }
    return isActive(job.state);
  });
}
