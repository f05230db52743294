// The app's addresses: REST paths on /v1 and the pages' hash routes. Pure. Every id is URL-encoded, since
// ids in a hash route come from the address bar.

const id = (value) => encodeURIComponent(value);
const withQuery = (path, query) => `${path}?${new URLSearchParams(query)}`;

export const paths = {
  jobs: (limit) => withQuery("/v1/jobs", { limit }),
  scenes: (limit) => withQuery("/v1/scenes", { limit }),
  job: (jobId) => `/v1/jobs/${id(jobId)}`,
  jobLogs: (jobId, offset, limit) => withQuery(`/v1/jobs/${id(jobId)}/logs`, { offset, limit }),
  scene: (sceneId) => `/v1/scenes/${id(sceneId)}`,
  reconstruction: (jobId) => `/v1/reconstructions/${id(jobId)}`,
  nerf: (jobId, sub = "") => `/v1/nerf/${id(jobId)}${sub ? `/${sub}` : ""}`,
  createReconstruction: "/v1/reconstructions",
  createScene: "/v1/scenes",
};

// #/ -> {page: "list"}; #/new -> {page: "new"}; #/jobs/{id} -> {page: "job", id}; #/scenes/{id} -> scene.
export function parseRoute(hash) {
  const [, kind, encoded] = (hash || "").replace(/^#\/?/, "/").split("/");
  let routeId = encoded;
  try { routeId = encoded && decodeURIComponent(encoded); } catch { /* malformed escape: kept as typed */ }
  if (kind === "new") return { page: "new" };
  if (kind === "jobs" && routeId) return { page: "job", id: routeId };
  if (kind === "scenes" && routeId) return { page: "scene", id: routeId };
  return { page: "list" };
}

export const routes = {
  list: "#/",
  upload: "#/new",
  job: (jobId) => `#/jobs/${id(jobId)}`,
  scene: (sceneId) => `#/scenes/${id(sceneId)}`,
};
