// #/ : the client's scenes and jobs, polled.
import { getJson } from "../api.js";
import { h, poll, progressBar, stateText } from "../dom.js";
import { localTime, percent } from "../format.js";
import { paths, routes } from "../urls.js";

const SCENES_SHOWN = 50;
const JOBS_SHOWN = 100;

const header = (titles) => h("thead", {}, h("tr", {}, titles.map((t) => h("th", {}, t))));
const progressCell = (fraction) => h("td", {}, progressBar(fraction), ` ${percent(fraction)}`);
const noneYet = (columns) => h("tr", {}, h("td", { colspan: columns, class: "muted" }, "none yet"));

export function listPage(main, page) {
  const scenes = h("tbody"), jobs = h("tbody");
  main.append(
    h("h1", {}, "Scenes and jobs"),
    h("p", {}, h("a", { href: routes.upload }, "Upload photos"), " to start a reconstruction or a whole scene."),
    h("h2", {}, "Scenes"),
    h("table", { id: "scenes" }, header(["Scene", "State", "Stage", "Progress", "Created"]), scenes),
    h("h2", {}, "Jobs"),
    h("table", { id: "jobs" }, header(["Job", "Kind", "State", "Stage", "Progress", "Created"]), jobs),
  );
  poll(page, async () => {
    const [sceneList, jobList] = await Promise.all([getJson(paths.scenes(SCENES_SHOWN)), getJson(paths.jobs(JOBS_SHOWN))]);
    scenes.replaceChildren(...sceneList.items.map((s) => h("tr", { dataset: { id: s.id, state: s.state } },
      h("td", {}, h("a", { href: routes.scene(s.id) }, s.id.slice(0, 8))), h("td", {}, stateText(s.state)),
      h("td", {}, s.stage || ""), progressCell(s.progress), h("td", {}, localTime(s.created_at)))));
    if (!sceneList.items.length) scenes.append(noneYet(5));
    jobs.replaceChildren(...jobList.items.map((j) => h("tr", { dataset: { id: j.id, state: j.state } },
      h("td", {}, h("a", { href: routes.job(j.id) }, j.id.slice(0, 8))), h("td", {}, j.kind),
      h("td", {}, stateText(j.state)), h("td", {}, j.stage || ""), progressCell(j.progress),
      h("td", {}, localTime(j.created_at)))));
    if (!jobList.items.length) jobs.append(noneYet(6));
  });
}
