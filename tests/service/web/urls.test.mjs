// REST paths and hash routes (service/web/js/urls.js).
import assert from "node:assert/strict";
import { test } from "node:test";

import { parseRoute, paths, routes } from "../../../service/web/js/urls.js";

test("REST paths carry the ids and query parameters", () => {
  assert.equal(paths.jobs(100), "/v1/jobs?limit=100");
  assert.equal(paths.scenes(50), "/v1/scenes?limit=50");
  assert.equal(paths.job("ab12"), "/v1/jobs/ab12");
  assert.equal(paths.jobLogs("ab12", 40, 1000), "/v1/jobs/ab12/logs?offset=40&limit=1000");
  assert.equal(paths.scene("s1"), "/v1/scenes/s1");
  assert.equal(paths.reconstruction("r1"), "/v1/reconstructions/r1");
  assert.equal(paths.nerf("n1"), "/v1/nerf/n1");
  assert.equal(paths.nerf("n1", "render"), "/v1/nerf/n1/render");
});

test("an id typed into the address bar cannot leave its path segment", () => {
  assert.equal(paths.job("../scenes?x=1"), "/v1/jobs/..%2Fscenes%3Fx%3D1");
  assert.equal(paths.nerf("a/b", "video"), "/v1/nerf/a%2Fb/video");
});

test("hash routes name the page and its id", () => {
  assert.deepEqual(parseRoute(""), { page: "list" });
  assert.deepEqual(parseRoute("#/"), { page: "list" });
  assert.deepEqual(parseRoute("#/new"), { page: "new" });
  assert.deepEqual(parseRoute("#/jobs/abc"), { page: "job", id: "abc" });
  assert.deepEqual(parseRoute("#scenes/def"), { page: "scene", id: "def" });
  assert.deepEqual(parseRoute("#/jobs/"), { page: "list" });
  assert.deepEqual(parseRoute("#/elsewhere/1"), { page: "list" });
  assert.deepEqual(parseRoute("#/jobs/%E0%A4%A"), { page: "job", id: "%E0%A4%A" });
});

test("routes and parseRoute agree", () => {
  for (const id of ["0123456789abcdef", "a b/c"]) {
    assert.deepEqual(parseRoute(routes.job(id)), { page: "job", id });
    assert.deepEqual(parseRoute(routes.scene(id)), { page: "scene", id });
  }
  assert.deepEqual(parseRoute(routes.upload), { page: "new" });
  assert.deepEqual(parseRoute(routes.list), { page: "list" });
});
