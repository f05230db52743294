// A job's log, followed while the job runs (the last LOG_LINES_KEPT lines, kept scrolled to the end).
import { getJson } from "../api.js";
import { h, poll } from "../dom.js";
import { isActive } from "../format.js";
import { paths } from "../urls.js";

const LOG_LINES_KEPT = 300;
const LOG_CHUNK_LINES = 1000;

export function logPanel(page, jobId) {
  const pre = h("pre", { class: "log", id: `log-${jobId}` });
  let offset = 0, lines = [];
  poll(page, async () => {
    const chunk = await getJson(paths.jobLogs(jobId, offset, LOG_CHUNK_LINES));
    offset = chunk.next_offset;
    if (chunk.lines.length) {
      lines = lines.concat(chunk.lines).slice(-LOG_LINES_KEPT);
      const atBottom = pre.scrollTop + pre.clientHeight >= pre.scrollHeight - 4;
      pre.textContent = lines.join("\n");
      if (atBottom) pre.scrollTop = pre.scrollHeight;
    }
    const job = await getJson(paths.job(jobId));
    return isActive(job.state) || chunk.lines.length > 0;
  });
  return h("div", { class: "panel" }, h("h2", {}, "Log"), pre);
}
