"""Service benchmark: job-status latency under load (polling clients, then render clients), and API
overhead against the CLI on Unity Hall.

1. `sfmnerf serve` runs in its own process (embedded defaults, a temporary data folder, loopback port).
   While a Unity Hall reconstruction runs, 50 concurrent clients poll GET /v1/jobs/{id}: requests per second
   and latency percentiles over that window.
   Then the server's CPU time per request with one client on an idle service (the per-request cost).
2. Renders: a tiny NeRF is trained through the API; then, for each count in --render-clients, that many
   clients POST /v1/nerf/{id}/render at 200x200 (a new camera each time, so no render is cached) for
   --render-seconds while 4 clients poll GET /v1/jobs/{id}: the status latency percentiles, and how the
   renders were answered (200, 503 + Retry-After, errors). --compare-root runs the same section against
   another checkout's service (e.g. /work/main, the code before renders left the API) in the same run.
   Load: --load-scenes clients (8) each POST a Unity Hall scene at the same moment (tiny budgets) and poll
   it to its end while --load-renderers clients (48) render and 4 poll GET /v1/jobs/{id}: the status
   latency percentiles (target p99 < 500 ms), scenes per hour, the API's peak RSS, alone and with its
   job and render processes, and how long it takes to exit on SIGTERM right after.
3. Upload -> finished Unity Hall through the API (POST, then polling every 50 ms) against
   `sfmnerf reconstruct` on the same input (a fresh process each time, as the API's job is), median of N runs,
   API and CLI runs interleaved.
4. A scene (POST /v1/scenes) on Unity Hall (course match files) and on strecha/fountain-P11 (11 photos of
   3072x2048, SIFT; the NeRF trains at --scene-max-side): seconds from the upload to the first orbit frame on
   disk and to the end, and each stage's seconds (its child jobs, first start to last end), against
   `sfmnerf scene` with the same options (its own per-stage timing, a fresh process).
5. The web app's job page of a reconstruction with a 10,000-point cloud in headless Chromium (Debian's
   /usr/bin/chromium, SwiftShader WebGL): first contentful paint, and the moment the 3D view is drawn with
   its controls attached (the page's `sfmnerf:view3d-ready` mark), median of N fresh page loads.

    python benchmarks/bench_service.py [--runs 3] [--clients 50] [--render-clients 8 60]
        [--compare-root ../main] [--scene-steps 200] [--scene-sets unity_hall fountain-P11] [--page-loads 5]
        [--load-scenes 8] [--load-renderers 48] [--load-scene-steps 50]
        [--sections renders load polling overhead scenes page]

The load generator shares the machine with the server and the job: numbers are for this machine and load.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import random
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from datetime import datetime
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))  # run as a script from anywhere: the tests' server helpers

from service.kinds import JobKind, JobState  # noqa: E402
from service.store import JobStore  # noqa: E402
from tests.service.conftest import TINY_MODEL_OPTIONS, tiny_nerf_npz, unity_hall_files  # noqa: E402
from tests.service.servers import free_port, start_server  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
UNITY_HALL = DATA / "unity_hall"
SCENE_SETS = {"unity_hall": UNITY_HALL, "fountain-P11": DATA / "strecha" / "fountain-P11"}
SECTIONS = ("renders", "load", "polling", "overhead", "scenes", "page")
LEGO_TINY = DATA / "lego_tiny.npz"
RENDER_SIDE = 200
STATUS_POLLERS = 4
LOAD_SCENE_MAX_SIDE = 100
"""The load scenes' NeRF trains on images at most this long (small: the figures are the API's, not NeRF's)."""
RSS_SAMPLE_SECONDS = 0.25
TINY_SIDE = 20
TINY_NERF = {
    "model": "vanilla",
    "steps": "60",
    "batch_rays": "64",
    "device": "cpu",
    "options": json.dumps(
        {
            "checkpoint_every": 30,
            "val_every": 1000,
            "seed": 0,
            "model_options": TINY_MODEL_OPTIONS,
        }
    ),
}
POLL_SECONDS = 0.05
JOB_TIMEOUT_SECONDS = 600.0
SCENE_TIMEOUT_SECONDS = 3600.0
CHROMIUM = "/usr/bin/chromium"


def wait_finished(client: httpx.Client, job_id: str) -> dict:
    deadline = time.monotonic() + JOB_TIMEOUT_SECONDS
    while time.monotonic() < deadline:
        job = client.get(f"/v1/jobs/{job_id}").json()
        if job["state"] in ("succeeded", "failed", "cancelled"):
            return job
        time.sleep(POLL_SECONDS)
    raise RuntimeError(f"job {job_id} did not finish")


async def poll_under_load(base_url: str, job_id: str, clients: int) -> tuple[list[float], float, int]:
    """Each client GETs the job in a loop until it has finished; (latencies s, window s, errors)."""
    latencies: list[float] = []
    errors = 0
    done = asyncio.Event()
    limits = httpx.Limits(max_connections=clients, max_keepalive_connections=clients)
    async with httpx.AsyncClient(base_url=base_url, limits=limits, timeout=30) as client:

        async def one_client() -> None:
            nonlocal errors
            while not done.is_set():
                start = time.perf_counter()
                try:
                    response = await client.get(f"/v1/jobs/{job_id}")
                    latencies.append(time.perf_counter() - start)
                    if response.status_code != 200:
                        errors += 1
                    elif response.json()["state"] in ("succeeded", "failed", "cancelled"):
                        done.set()
                except httpx.HTTPError:
                    errors += 1

        began = time.perf_counter()
        await asyncio.gather(*(one_client() for _ in range(clients)))
        return latencies, time.perf_counter() - began, errors


async def render_loop(
    client: httpx.AsyncClient, job_id: str, until: Callable[[], bool], answers: dict
) -> None:
    """POSTs renders of the NeRF job from a new camera each time (no cache hit) until `until()`; counts the
    answers by status (429/503: waits its Retry-After)."""
    rng = random.Random()
    while not until():
        camera = {
            "eye": [rng.uniform(2, 4), rng.uniform(-4, -2), rng.uniform(0.5, 2)],
            "look_at": [0.0, 0.0, 0.0],
            "width": RENDER_SIDE,
            "height": RENDER_SIDE,
        }
        try:
            response = await client.post(f"/v1/nerf/{job_id}/render", json=camera)
            key = str(response.status_code)
            if response.status_code in (429, 503):
                await asyncio.sleep(float(response.headers.get("Retry-After", "1")))
        except httpx.HTTPError as error:
            key = type(error).__name__
        answers[key] = answers.get(key, 0) + 1


async def status_loop(
    client: httpx.AsyncClient, job_id: str, until: Callable[[], bool], latencies: list, answers: dict
) -> None:
    """GET /v1/jobs/{id} every 50 ms until `until()`, recording each request's latency."""
    while not until():
        start = time.perf_counter()
        try:
            await client.get(f"/v1/jobs/{job_id}")
            latencies.append(time.perf_counter() - start)
        except httpx.HTTPError:
            answers["status error"] = answers.get("status error", 0) + 1
        await asyncio.sleep(0.05)


async def status_under_renders(base_url: str, job_id: str, clients: int, seconds: float) -> dict:
    """`clients` render loops and STATUS_POLLERS status loops for `seconds`; latencies and answer counts."""
    latencies: list[float] = []
    answers: dict[str, int] = {}
    deadline = time.perf_counter() + seconds

    def until() -> bool:
        return time.perf_counter() >= deadline

    limits = httpx.Limits(max_connections=clients + STATUS_POLLERS + 4)
    async with httpx.AsyncClient(base_url=base_url, limits=limits, timeout=120) as client:
        await asyncio.gather(
            *(render_loop(client, job_id, until, answers) for _ in range(clients)),
            *(status_loop(client, job_id, until, latencies, answers) for _ in range(STATUS_POLLERS)),
        )
    return {"latencies": latencies, "answers": answers}


def process_tree_rss(root_pid: int) -> tuple[int, int]:
    """(RSS of the process, RSS of it and every descendant), bytes (Linux /proc)."""
    children: dict[int, list[int]] = {}
    rss: dict[int, int] = {}
    page = os.sysconf("SC_PAGE_SIZE")
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:  # it exited meanwhile
            continue
        children.setdefault(int(fields[1]), []).append(int(entry.name))
        rss[int(entry.name)] = int(fields[21]) * page
    tree, pending = 0, [root_pid]
    while pending:
        pid = pending.pop()
        tree += rss.get(pid, 0)
        pending += children.get(pid, [])
    return rss.get(root_pid, 0), tree


async def peak_rss(pid: int, until: Callable[[], bool]) -> tuple[int, int]:
    """The peak of process_tree_rss(pid), sampled every RSS_SAMPLE_SECONDS until `until()`."""
    peak_api, peak_tree = 0, 0
    while not until():
        api, tree = await asyncio.to_thread(process_tree_rss, pid)
        peak_api, peak_tree = max(peak_api, api), max(peak_tree, tree)
        await asyncio.sleep(RSS_SAMPLE_SECONDS)
    return peak_api, peak_tree


async def scenes_under_renders(
    base_url: str, server_pid: int, nerf_id: str, scenes: int, renderers: int, scene_options: dict
) -> dict:
    """`scenes` clients each POST a Unity Hall scene at the same moment and poll it to its end, while
    `renderers` clients render views of the NeRF job and STATUS_POLLERS poll its status; the status
    latencies, render answers, each scene's seconds, and the API's peak RSS (alone and with its children)."""
    latencies: list[float] = []
    answers: dict[str, int] = {}
    ended: list[tuple[str, float]] = []
    photos = unity_hall_files(UNITY_HALL)
    begun = time.perf_counter()

    def until() -> bool:
        return len(ended) == scenes or time.perf_counter() - begun > SCENE_TIMEOUT_SECONDS

    async def one_scene(client: httpx.AsyncClient) -> None:
        response = await client.post("/v1/scenes", files=photos, data=scene_options)
        if response.status_code != 202:
            ended.append((f"refused {response.status_code}", time.perf_counter() - begun))
            return
        state = "running"
        while state == "running" and time.perf_counter() - begun < SCENE_TIMEOUT_SECONDS:
            await asyncio.sleep(0.5)
            try:
                state = (await client.get(response.headers["Location"])).json()["state"]
            except httpx.HTTPError as error:
                answers[f"scene status {type(error).__name__}"] = (
                    answers.get(f"scene status {type(error).__name__}", 0) + 1
                )
        ended.append((state, time.perf_counter() - begun))

    limits = httpx.Limits(max_connections=scenes + renderers + STATUS_POLLERS + 4)
    async with httpx.AsyncClient(base_url=base_url, limits=limits, timeout=300) as client:
        _, (api_rss, tree_rss), *_ = await asyncio.gather(
            asyncio.gather(*(one_scene(client) for _ in range(scenes))),
            peak_rss(server_pid, until),
            *(render_loop(client, nerf_id, until, answers) for _ in range(renderers)),
            *(status_loop(client, nerf_id, until, latencies, answers) for _ in range(STATUS_POLLERS)),
        )
    return {"latencies": latencies, "answers": answers, "ended": ended, "api_rss": api_rss,
            "tree_rss": tree_rss}  # fmt: skip


def trained_tiny_nerf(client: httpx.Client) -> str:
    """The id of a tiny NeRF trained through the API (the renders' model)."""
    files = {"dataset": ("tiny.npz", tiny_nerf_npz(LEGO_TINY, TINY_SIDE), "application/octet-stream")}
    job_id = client.post("/v1/nerf", files=files, data=TINY_NERF).json()["id"]
    assert wait_finished(client, job_id)["state"] == "succeeded"
    return job_id


def load_section(args: argparse.Namespace) -> None:
    """Scenes submitted at once while clients render: status latency, scenes per hour, API peak RSS."""
    scene_options = {
        "steps": str(args.load_scene_steps),
        "batch_rays": "256",
        "options": json.dumps({"max_side": LOAD_SCENE_MAX_SIDE}),
        "orbit_frames": str(args.load_orbit_frames),
        "orbit_max_side": "48",
        "held_out_max_side": "40",
    }
    with (
        tempfile.TemporaryDirectory(prefix="sfmnerf-bench-") as tmp,
        open(Path(tmp) / "server.log", "wb") as log,
    ):
        port = free_port()
        server = start_server(Path(tmp) / "data", port, log=log)
        base_url = f"http://127.0.0.1:{port}"
        try:
            with httpx.Client(base_url=base_url, timeout=60) as client:
                nerf_id = trained_tiny_nerf(client)
            row = asyncio.run(scenes_under_renders(
                base_url, server.pid, nerf_id, args.load_scenes, args.load_renderers, scene_options
            ))  # fmt: skip
            stopping = time.perf_counter()  # the renders' clients are gone; their requests may still run
            server.terminate()
            server.wait(timeout=120)
            exit_seconds = time.perf_counter() - stopping
        finally:
            if server.poll() is None:
                server.kill()
                server.wait()
        tracebacks = (Path(tmp) / "server.log").read_text(errors="replace").count("Traceback")
    ms = np.array(row["latencies"]) * 1000
    states = ", ".join(f"{k}: {v}" for k, v in sorted(Counter(state for state, _ in row["ended"]).items()))
    last = max(seconds for _, seconds in row["ended"])
    succeeded = sum(state == "succeeded" for state, _ in row["ended"])
    answers = ", ".join(f"{k}: {v}" for k, v in sorted(row["answers"].items()))
    print(
        f"{args.load_scenes} clients each POST a Unity Hall scene at once ({args.load_scene_steps} NeRF "
        f"steps of 256 rays at <= {LOAD_SCENE_MAX_SIDE} px, {args.load_orbit_frames} orbit frames) while "
        f"{args.load_renderers} clients render {RENDER_SIDE}x{RENDER_SIDE} views and {STATUS_POLLERS} poll "
        "GET /v1/jobs/{id}; embedded defaults"
    )
    print("| status requests | p50 ms | p99 ms | max ms | scenes | last scene ended s | succeeded per hour | "
          "API peak RSS MB | API tree peak RSS MB | render answers |")  # fmt: skip
    print("|---:|---:|---:|---:|---|---:|---:|---:|---:|---|")
    print(
        f"| {len(ms)} | {np.percentile(ms, 50):.1f} | {np.percentile(ms, 99):.1f} | {ms.max():.1f} | "
        f"{states} | {last:.1f} | {3600 * succeeded / last:.0f} | {row['api_rss'] / 2**20:.0f} | "
        f"{row['tree_rss'] / 2**20:.0f} | {answers} |"
    )
    print(f"tracebacks in the server's log: {tracebacks}; exit after SIGTERM: {exit_seconds:.1f} s")
    print(flush=True)


def render_section(root: Path, counts: list[int], seconds: float) -> list[tuple[int, dict]]:
    """The render-load rows for the service in source tree `root`."""
    rows = []
    with tempfile.TemporaryDirectory(prefix="sfmnerf-bench-") as tmp:
        port = free_port()
        server = start_server(Path(tmp) / "data", port, root=root)
        base_url = f"http://127.0.0.1:{port}"
        try:
            with httpx.Client(base_url=base_url, timeout=60) as client:
                job_id = trained_tiny_nerf(client)
            for count in counts:
                rows.append((count, asyncio.run(status_under_renders(base_url, job_id, count, seconds))))
        finally:
            server.terminate()
            server.wait(timeout=60)
    return rows


def print_render_rows(label: str, rows: list[tuple[int, dict]]) -> None:
    for count, row in rows:
        ms = np.array(row["latencies"]) * 1000
        answers = ", ".join(f"{k}: {v}" for k, v in sorted(row["answers"].items()))
        print(
            f"| {label} | {count} | {len(ms)} | {np.percentile(ms, 50):.1f} | {np.percentile(ms, 99):.1f} | "
            f"{ms.max():.1f} | {answers} |"
        )


def server_cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def sequential_cost(client: httpx.Client, pid: int, path: str, requests: int) -> tuple[float, float]:
    """(server CPU ms, wall ms) per request, one client, nothing else running in the service."""
    for _ in range(20):
        client.get(path)
    cpu, start = server_cpu_seconds(pid), time.perf_counter()
    for _ in range(requests):
        client.get(path)
    wall = time.perf_counter() - start
    return 1000 * (server_cpu_seconds(pid) - cpu) / requests, 1000 * wall / requests


def api_run(client: httpx.Client, files: list) -> float:
    start = time.perf_counter()
    job_id = client.post("/v1/reconstructions", files=files).json()["id"]
    job = wait_finished(client, job_id)
    assert job["state"] == "succeeded", job
    return time.perf_counter() - start


def cli_run(out_dir: Path) -> float:
    start = time.perf_counter()
    subprocess.run(
        [
            sys.executable,
            "-c",
            "from service.cli import main; main()",
            "reconstruct",
            str(UNITY_HALL),
            "--out",
            str(out_dir),
        ],
        cwd=ROOT,
        check=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    return time.perf_counter() - start


def scene_run(client: httpx.Client, files: list, data_dir: Path, options: dict) -> dict:
    """A scene through the API: seconds to the first orbit frame on disk, to the end, and per stage."""
    start = time.perf_counter()
    scene_id = client.post("/v1/scenes", files=files, data=options).json()["id"]
    first_frame = None
    while (scene := client.get(f"/v1/scenes/{scene_id}").json())["state"] == "running":
        views = scene["stages"][2]["job_ids"]
        if (
            first_frame is None
            and views
            and (data_dir / "jobs" / views[0] / "output" / "orbit_000.png").exists()
        ):
            first_frame = time.perf_counter() - start
        assert time.perf_counter() - start < SCENE_TIMEOUT_SECONDS, scene
        time.sleep(POLL_SECONDS)
    total = time.perf_counter() - start
    assert scene["state"] == "succeeded", scene
    stages = {}
    for stage in scene["stages"]:
        jobs = [client.get(f"/v1/jobs/{job_id}").json() for job_id in stage["job_ids"]]
        began = min(datetime.fromisoformat(job["started_at"]) for job in jobs)
        ended = max(datetime.fromisoformat(job["finished_at"]) for job in jobs)
        stages[stage["name"]] = (ended - began).total_seconds()
    return {"first_frame": first_frame, "total": total, "stages": stages, "scene": scene}


def scene_files(folder: Path) -> list:
    """The multipart `files` of a scene upload of a folder: its photos, match files and calibration.txt."""
    if list(folder.glob("matching*.txt")):
        return unity_hall_files(folder)
    photos = [("images", (p.name, p.read_bytes(), "image/jpeg")) for p in sorted(folder.glob("*.jpg"))]
    calibration = ("calibration.txt", (folder / "calibration.txt").read_bytes(), "text/plain")
    return [*photos, ("calibration", calibration)]


def cli_scene_run(photos_dir: Path, out_dir: Path, options: dict) -> dict:
    """`sfmnerf scene` with the same options in a fresh process; its wall time and per-stage seconds."""
    start = time.perf_counter()
    run = subprocess.run(
        [sys.executable, "-c", "from service.cli import main; main()", "scene", str(photos_dir), "--out",
         str(out_dir), "--steps", options["steps"], "--orbit-frames", options["orbit_frames"],
         "--options", options["options"]],
        cwd=ROOT, check=True, capture_output=True, text=True,
    )  # fmt: skip
    total = time.perf_counter() - start
    line = next(x for x in run.stdout.splitlines() if x.startswith("seconds per stage: "))
    stages = {name: float(value) for name, value in (p.split() for p in line.split(": ", 1)[1].split(", "))}
    return {"total": total, "stages": stages}


def page_job_with_points(data_dir: Path, reconstruction_id: str, count: int) -> str:
    """A succeeded reconstruction job like `reconstruction_id`, its cloud resampled to `count` points."""
    from estimation.io.export import read_ply, write_ply

    store = JobStore(f"sqlite:///{data_dir / 'sfmnerf.sqlite'}")
    job = store.create(JobKind.reconstruction, {})
    attempt = store.claim(job.id, worker="benchmark")
    shutil.copytree(data_dir / "jobs" / reconstruction_id / "output", data_dir / "jobs" / job.id / "output")
    output = data_dir / "jobs" / job.id / "output"
    points, colors = read_ply(output / "points.ply")
    rng = np.random.default_rng(0)
    picked = rng.integers(0, len(points), count)
    spread = 0.01 * np.linalg.norm(points.std(axis=0))
    write_ply(output / "points.ply", points[picked] + rng.normal(0, spread, (count, 3)), colors[picked])
    report = json.loads((output / "report.json").read_text())
    (output / "report.json").write_text(json.dumps({**report, "points": count}))
    store.finish(job.id, attempt, JobState.succeeded, result={"points": count})
    store.dispose()
    return job.id


def page_timings(base_url: str, job_id: str, loads: int) -> list[tuple[float, float]]:
    """(first contentful paint ms, 3D view ready ms) of fresh loads of the job page."""
    from playwright.sync_api import sync_playwright

    timings = []
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=["--enable-unsafe-swiftshader"])
        for _ in range(loads):
            context = browser.new_context(viewport={"width": 1200, "height": 900})
            page = context.new_page()
            page.goto(f"{base_url}/#/jobs/{job_id}")
            page.wait_for_selector("#view3d[data-ready=true]", timeout=120_000)
            timings.append(tuple(page.evaluate(
                "['first-contentful-paint', 'sfmnerf:view3d-ready']"
                ".map((name) => performance.getEntriesByName(name)[0].startTime)"
            )))  # fmt: skip
            context.close()
        browser.close()
    return timings


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sections", nargs="+", choices=SECTIONS, default=list(SECTIONS))
    parser.add_argument("--runs", type=int, default=3, help="API and CLI runs for the overhead ratio.")
    parser.add_argument("--clients", type=int, default=50, help="Concurrent clients polling the job.")
    parser.add_argument("--sequential", type=int, default=1000, help="Requests for the per-request cost.")
    parser.add_argument("--scene-sets", nargs="+", choices=list(SCENE_SETS), default=list(SCENE_SETS))
    parser.add_argument("--scene-steps", type=int, default=200, help="NeRF steps of the scene runs.")
    parser.add_argument(
        "--scene-max-side", type=int, default=400, help="Long side of the scenes' NeRF training images."
    )
    parser.add_argument("--orbit-frames", type=int, default=12, help="Orbit frames of the scene runs.")
    parser.add_argument("--page-loads", type=int, default=5, help="Fresh loads of the job page.")
    parser.add_argument("--page-points", type=int, default=10_000, help="Points in the page's cloud.")
    parser.add_argument(
        "--render-clients", type=int, nargs="+", default=[8, 60], help="Render client counts."
    )
    parser.add_argument("--render-seconds", type=float, default=30.0, help="Window of each render load.")
    parser.add_argument("--load-scenes", type=int, default=8, help="Scenes submitted at once (load).")
    parser.add_argument("--load-renderers", type=int, default=48, help="Render clients beside them (load).")
    parser.add_argument("--load-scene-steps", type=int, default=20, help="NeRF steps of those scenes.")
    parser.add_argument("--load-orbit-frames", type=int, default=4, help="Orbit frames of those scenes.")
    parser.add_argument(
        "--compare-root", type=Path, default=None, help="Another checkout to run side by side."
    )
    args = parser.parse_args()
    sections = set(args.sections)
    if "renders" in sections:
        print_render_section(args)
    if "load" in sections:
        load_section(args)
    if not sections - {"renders", "load"}:
        return
    scene_options = {
        "steps": str(args.scene_steps),
        "orbit_frames": str(args.orbit_frames),
        "options": json.dumps({"max_side": args.scene_max_side}),
    }
    files = unity_hall_files(UNITY_HALL)
    with tempfile.TemporaryDirectory(prefix="sfmnerf-bench-") as tmp:
        data_dir = Path(tmp) / "data"
        port = free_port()
        server = start_server(data_dir, port)
        base_url = f"http://127.0.0.1:{port}"
        try:
            with httpx.Client(base_url=base_url, timeout=120) as client:
                job_id = client.post("/v1/reconstructions", files=files).json()["id"]
                if "polling" in sections:
                    latencies, window, errors = asyncio.run(poll_under_load(base_url, job_id, args.clients))
                assert wait_finished(client, job_id)["state"] == "succeeded"
                if "polling" in sections:
                    cpu_ms, wall_ms = sequential_cost(
                        client, server.pid, f"/v1/jobs/{job_id}", args.sequential
                    )
                    print_polling(args, latencies, window, errors, cpu_ms, wall_ms)
                if "overhead" in sections:
                    api_times, cli_times = [], []
                    for run in range(args.runs):  # interleaved, so both see the same machine load
                        api_times.append(api_run(client, files))
                        cli_times.append(cli_run(Path(tmp) / f"cli{run}"))
                    print_overhead(args, api_times, cli_times)
                if "scenes" in sections:
                    for name in args.scene_sets:
                        folder = SCENE_SETS[name]
                        api_scene = scene_run(client, scene_files(folder), data_dir, scene_options)
                        cli_scene = cli_scene_run(folder, Path(tmp) / f"cli-scene-{name}", scene_options)
                        print_scene(args, name, api_scene, cli_scene)
                if "page" in sections:
                    page_job = page_job_with_points(data_dir, job_id, args.page_points)
                    print_page(args, page_timings(base_url, page_job, args.page_loads))
        finally:
            server.terminate()
            server.wait(timeout=30)


def print_render_section(args: argparse.Namespace) -> None:
    roots = [("this tree", ROOT)] + (
        [(str(args.compare_root), args.compare_root.resolve())] if args.compare_root else []
    )
    render_rows = [
        (label, render_section(root, args.render_clients, args.render_seconds)) for label, root in roots
    ]
    print(
        f"GET /v1/jobs/{{id}} ({STATUS_POLLERS} pollers) while N clients render {RENDER_SIDE}x{RENDER_SIDE} "
        f"views of a tiny NeRF, {args.render_seconds:g} s per row"
    )
    print("| service | render clients | status requests | p50 ms | p99 ms | max ms | render answers |")
    print("|---|---:|---:|---:|---:|---:|---|")
    for label, rows in render_rows:
        print_render_rows(label, rows)
    print(flush=True)


def print_polling(
    args: argparse.Namespace, latencies: list, window: float, errors: int, cpu_ms: float, wall_ms: float
) -> None:
    ms = np.array(latencies) * 1000
    print(
        f"GET /v1/jobs/{{id}} with {args.clients} concurrent clients while a Unity Hall reconstruction runs"
    )
    print("| requests | window s | RPS | p50 ms | p99 ms | max ms | errors |")
    print("|---:|---:|---:|---:|---:|---:|---:|")
    print(
        f"| {len(ms)} | {window:.1f} | {len(ms) / window:.0f} | {np.percentile(ms, 50):.1f} | "
        f"{np.percentile(ms, 99):.1f} | {ms.max():.1f} | {errors} |"
    )
    print()
    print(f"One client, {args.sequential} sequential GET /v1/jobs/{{id}} on an idle service")
    print("| server CPU ms / request | wall ms / request | implied ceiling per core, RPS |")
    print("|---:|---:|---:|")
    print(f"| {cpu_ms:.2f} | {wall_ms:.2f} | {1000 / cpu_ms:.0f} |")
    print(flush=True)


def print_overhead(args: argparse.Namespace, api_times: list[float], cli_times: list[float]) -> None:
    api_median, cli_median = statistics.median(api_times), statistics.median(cli_times)
    print(f"Unity Hall upload -> finished, median of {args.runs} runs")
    print("| path | median s | runs s |")
    print("|---|---:|---|")
    api_runs = ", ".join(f"{t:.2f}" for t in api_times)
    print(f"| API (POST + job process + polling) | {api_median:.2f} | {api_runs} |")
    print(
        f"| CLI (`sfmnerf reconstruct`, fresh process) | {cli_median:.2f} | "
        f"{', '.join(f'{t:.2f}' for t in cli_times)} |"
    )
    print(f"| overhead ratio API / CLI | {api_median / cli_median:.2f} | |")
    print(flush=True)


def print_scene(args: argparse.Namespace, name: str, api_scene: dict, cli_scene: dict) -> None:
    print(f"{name} scene ({args.scene_steps} NeRF steps at <= {args.scene_max_side} px, fast model, "
          f"{args.orbit_frames} orbit frames): API vs `sfmnerf scene`")  # fmt: skip
    print("| | API s | CLI s | API / CLI |")
    print("|---|---:|---:|---:|")
    for stage in ("reconstruction", "nerf", "views"):
        api, cli = api_scene["stages"][stage], cli_scene["stages"][stage]
        print(f"| {stage} | {api:.1f} | {cli:.1f} | {api / cli:.2f} |")
    print(f"| upload -> first orbit frame on disk | {api_scene['first_frame']:.1f} | | |")
    api, cli = api_scene["total"], cli_scene["total"]
    print(f"| upload -> scene finished (wall) | {api:.1f} | {cli:.1f} | {api / cli:.2f} |")
    print(flush=True)


def print_page(args: argparse.Namespace, paints: list[tuple[float, float]]) -> None:
    fcp, ready = (np.median([t[i] for t in paints]) for i in (0, 1))
    loads = f"median of {args.page_loads} loads"
    print(f"Job page with a {args.page_points}-point cloud, headless Chromium, {loads}")
    print("| first contentful paint ms | 3D view drawn and interactive ms | loads ms |")
    print("|---:|---:|---|")
    print(f"| {fcp:.0f} | {ready:.0f} | {', '.join(f'{a:.0f}/{b:.0f}' for a, b in paints)} |")
    print(flush=True)


if __name__ == "__main__":
    main()
