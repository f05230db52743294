"""The documentation stays usable and true: a short README for users, links that lead somewhere, files and
Python names that exist, the settings table as the settings class defines it, and files that speak of the
product only."""

from __future__ import annotations

import argparse
import importlib.util
import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
DOCUMENTS = [README, *sorted((ROOT / "docs").glob("*.md")), ROOT / "benchmarks" / "RESULTS.md"]
README_MAX_LINES = 200

LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
FENCE = re.compile(r"^```.*?^```", re.M | re.S)
WORK_PROCESS_WORDS = {
    "a numbered stop": re.compile(r"\bstop [0-9]+\b", re.I),
    "a branch name": re.compile(r"\bbranch (sfm|nerf|svc|service)[-a-z0-9]*", re.I),
    "engineers": re.compile(r"\bengineers?\b", re.I),
    "a benchmark lock": re.compile(r"\bbench(mark)?[-. _]lock", re.I),
}


def load_script(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up while the script runs
    spec.loader.exec_module(module)
    return module


def heading_anchors(markdown: str) -> set[str]:
    """GitHub's anchors of a document's headings: lower case, punctuation dropped, spaces as hyphens."""
    anchors = set()
    for line in FENCE.sub("", markdown).splitlines():
        if match := re.match(r"#{1,6}\s+(.*)", line):
            title = match.group(1).strip().lower()
            anchors.add(re.sub(r"[^\w\- ]", "", title).replace(" ", "-"))
    return anchors


def relative_links(document: Path) -> list[str]:
    text = FENCE.sub("", document.read_text(encoding="utf-8"))
    return [target for target in LINK.findall(text) if not re.match(r"[a-z][a-z0-9+.-]*:", target)]


def tracked_files() -> list[Path]:
    try:
        listing = subprocess.run(
            ["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True, text=True
        ).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout: the tracked files are unknown")
    return [ROOT / name for name in listing.split("\0") if name]


CODE_PATH = re.compile(r"`([A-Za-z0-9_.-]+(?:/[A-Za-z0-9_.-]+)*\.(?:py|js|css|html|yaml|sh|toml|mako))\b")
DOTTED_NAME = re.compile(r"`((?:estimation|neural|service)(?:\.[A-Za-z_][A-Za-z0-9_]*)+)")


def test_every_file_the_documents_name_exists():
    """A file named in backticks (`estimation/geometry/ransac.py`, `mapper/incremental.py`, `bench_sfm.py`)
    is the end of a tracked file's path."""
    tracked = ["/" + str(path.relative_to(ROOT)) for path in tracked_files()]
    missing = [
        f"{document.relative_to(ROOT)}: {name}"
        for document in DOCUMENTS
        for name in CODE_PATH.findall(document.read_text(encoding="utf-8"))
        if not any(path.endswith("/" + name) for path in tracked)
    ]
    assert not missing, "; ".join(missing)


def test_every_python_name_the_documents_name_exists():
    """`estimation.pipeline.initial_intrinsics`, `neural.data.Dataset`, ...: a module, then attributes."""
    missing = []
    for document in DOCUMENTS:
        for name in sorted(set(DOTTED_NAME.findall(document.read_text(encoding="utf-8")))):
            parts = name.split(".")
            for length in range(len(parts), 0, -1):
                try:
                    found = importlib.import_module(".".join(parts[:length]))
                    break
                except ModuleNotFoundError:
                    continue
            for attribute in parts[length:]:
                found = getattr(found, attribute, None)
            if found is None:
                missing.append(f"{document.relative_to(ROOT)}: {name}")
    assert not missing, "; ".join(missing)


def test_readme_is_short_enough_to_read_in_one_sitting():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines (at most {README_MAX_LINES})"


def test_readme_shows_the_web_app_and_links_every_document():
    links = set(relative_links(README))
    assert "docs/images/scene-page.png" in links
    for document in DOCUMENTS[1:]:
        assert str(document.relative_to(ROOT)) in links, f"README.md does not link {document.name}"


@pytest.mark.parametrize("document", DOCUMENTS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_leads_to_a_file_and_heading(document):
    broken = []
    for target in relative_links(document):
        path, _, anchor = target.partition("#")
        destination = (document.parent / path).resolve() if path else document
        if not destination.exists():
            broken.append(f"{target}: no such file")
        elif (
            anchor
            and destination.suffix == ".md"
            and anchor not in heading_anchors(destination.read_text(encoding="utf-8"))
        ):
            broken.append(f"{target}: no such heading")
    assert not broken, f"{document.relative_to(ROOT)}: " + "; ".join(broken)


def test_heading_anchors_follow_github():
    anchors = heading_anchors("# Checkerboard calibration (`sfmnerf calibrate`)\n## API (all under `/v1`)\n")
    assert anchors == {"checkerboard-calibration-sfmnerf-calibrate", "api-all-under-v1"}


def test_settings_table_is_the_one_the_settings_class_generates():
    settings_table = load_script("settings_table")
    text = settings_table.DOC.read_text(encoding="utf-8")
    assert settings_table.replace_table(text, settings_table.settings_table()) == text, (
        "docs/service.md's settings table differs from the settings class: "
        "run python3 scripts/settings_table.py --write"
    )


def test_settings_table_has_one_row_per_setting():
    from service.settings import ServiceSettings

    rows = load_script("settings_table").settings_table().splitlines()[2:]
    variables = [row.split("|")[1].strip(" `") for row in rows]
    assert variables == [f"SFMNERF_{name.upper()}" for name in ServiceSettings.model_fields]


def test_files_speak_of_the_product_not_of_how_it_was_made():
    found = []
    for path in tracked_files():
        relative = path.relative_to(ROOT)
        if relative.parts[0] == "tests" or not path.is_file():
            continue
        try:
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError:
            continue  # images and other binary files
        for number, line in enumerate(text.splitlines(), 1):
            for what, pattern in WORK_PROCESS_WORDS.items():
                if match := pattern.search(line):
                    found.append(f"{relative}:{number}: {what} ({match.group(0)!r})")
    assert not found, "\n".join(found)


@pytest.mark.parametrize(
    "line",
    [
        "measured on stop 21's main",
        "branch sfm-verify3 (22:06 UTC)",
        "other engineers' work",
        "flock /tmp/sfmnerf-bench.lock python benchmarks/bench_sfm.py",
        "under the benchmark lock",
    ],
)
def test_work_process_words_are_recognised(line):
    assert any(pattern.search(line) for pattern in WORK_PROCESS_WORDS.values())


@pytest.mark.parametrize(
    "line",
    ["a job stops when cancelled", "stop the service with Ctrl-C", "the flock of points", "git branch"],
)
def test_ordinary_words_are_not_taken_for_work_process_words(line):
    assert not any(pattern.search(line) for pattern in WORK_PROCESS_WORDS.values())


def write_package(root: Path, files: dict[str, str]) -> None:
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)


def test_import_graph_puts_every_importer_above_what_it_imports(tmp_path):
    import_graph = load_script("import_graph")
    write_package(
        tmp_path,
        {
            "pkg/__init__.py": "from pkg.core.base import Thing\n",
            "pkg/core/__init__.py": "",
            "pkg/core/base.py": "Thing = 1\n",
            "pkg/middle.py": "from pkg import Thing\n",  # through the package's re-export
            "pkg/top.py": "def run():\n    from . import middle\n",  # inside a function, relative
        },
    )
    modules = import_graph.module_graph(import_graph.read_modules(tmp_path, ["pkg"]))
    graph = import_graph.node_graph(modules, depth=2)
    assert graph == {"pkg.core": set(), "pkg.middle": {"pkg.core"}, "pkg.top": {"pkg.middle"}}
    component = import_graph.strongly_connected(graph)
    assert import_graph.floors(graph, component) == {"pkg.core": 0, "pkg.middle": 1, "pkg.top": 2}


def test_import_graph_draws_a_cycle_on_one_floor_in_red(tmp_path):
    import_graph = load_script("import_graph")
    write_package(
        tmp_path,
        {
            "pkg/__init__.py": "",
            "pkg/a.py": "from pkg.b import y\nx = 1\n",
            "pkg/b.py": "def f():\n    from pkg.a import x\ny = 2\n",
            "pkg/c.py": "import pkg.a\n",
        },
    )
    modules = import_graph.module_graph(import_graph.read_modules(tmp_path, ["pkg"]))
    graph = import_graph.node_graph(modules, depth=2)
    component = import_graph.strongly_connected(graph)
    assert component["pkg.a"] == component["pkg.b"] != component["pkg.c"]
    assert import_graph.floors(graph, component) == {"pkg.a": 0, "pkg.b": 0, "pkg.c": 1}
    svg = import_graph.render_svg(graph, depth=2)
    assert svg.count(f'stroke="{import_graph.CYCLE_COLOUR}" stroke-width="2"') == 2  # a and b, not c
    assert "1 import cycle(s) in red" in svg


def test_heldout_error_column_bands_give_each_bands_share_of_the_error_and_its_psnr():
    heldout_error = load_script("heldout_error")
    error = np.full((4, 10), 1e-2)
    error[:, 9] = 1e-1  # the right tenth: 10 of the 19 units of error
    text = heldout_error.column_bands(error, [0.5, 0.9])
    assert text == ("columns 0-5: 26.3% of it, PSNR 20.00 dB; columns 5-9: 21.1% of it, PSNR 20.00 dB; "
                    "columns 9-10: 52.6% of it, PSNR 10.00 dB")


@pytest.mark.parametrize("splits", ["0.9,0.2", "0,0.5", "0.5,1", "x"])
def test_heldout_error_refuses_column_splits_that_are_no_increasing_fractions(splits):
    heldout_error = load_script("heldout_error")
    with pytest.raises(argparse.ArgumentTypeError, match=re.escape(repr(splits))):
        heldout_error.width_fractions(splits)
    assert heldout_error.width_fractions("0.25,0.9") == [0.25, 0.9]


def test_heldout_error_dominant_plane_is_the_plane_most_points_lie_on():
    heldout_error = load_script("heldout_error")
    rng = np.random.default_rng(0)
    on_plane = np.column_stack([rng.uniform(-1, 1, 300), rng.uniform(-1, 1, 300), np.full(300, 0.5)])
    scattered = rng.uniform(-1, 1, (100, 3))
    normal, offset = heldout_error.dominant_plane(np.vstack([on_plane, scattered]), 0.01)
    assert np.allclose(abs(normal[2]), 1.0, atol=1e-6)
    assert np.isclose(offset * np.sign(normal[2]), 0.5, atol=1e-6)


def test_heldout_error_counts_a_ray_unseen_where_it_meets_the_plane_outside_every_training_view():
    heldout_error = load_script("heldout_error")
    # One training camera at the origin looking down -z (OpenGL axes), 90 degrees wide: it sees the plane
    # z = -1 for |x|, |y| < 1. The rays start 3 units to the right of it, also looking down -z.
    dataset = SimpleNamespace(width=100, height=100, fx=50.0, fy=50.0, cx=50.0, cy=50.0, poses=[np.eye(4)])
    plane = (np.array([0.0, 0.0, 1.0]), -1.0)
    origins = np.tile([3.0, 0.0, 0.0], (3, 1))
    directions = np.array([[-3.0, 0.0, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, 1.0]])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    seen = heldout_error.seen_on_plane(origins, directions, plane, dataset, np.array([0]))
    # Meets the plane at (0, 0, -1): seen; at (3, 0, -1): outside the view; away from the plane: counted seen.
    assert seen.tolist() == [True, False, True]


def test_heldout_error_depth_error_is_the_median_relative_gap_at_the_photos_own_points():
    heldout_error = load_script("heldout_error")
    import torch

    class FlatModel(torch.nn.Module):
        """Every ray ends 2 units away."""

        def render_rays(self, origins, directions, *args, **kwargs):
            depth = torch.full((len(origins),), 2.0)
            return SimpleNamespace(rgb=torch.zeros(len(origins), 3), depth=depth,
                                   opacity=torch.ones_like(depth))

    depth_rays = SimpleNamespace(image=np.array([0, 0, 0, 1]), u=np.array([1.0, 2.0, 3.0, 4.0]),
                                 v=np.array([1.0, 2.0, 3.0, 4.0]), distance=np.array([2.0, 2.5, 1.0, 2.0]))
    dataset = SimpleNamespace(depth_rays=depth_rays, poses=np.stack([np.eye(4)] * 3), fx=10.0, fy=10.0,
                              cx=5.0, cy=5.0)
    run = SimpleNamespace(model=FlatModel(), scene=SimpleNamespace(near=0.1, far=10.0),
                          background=torch.zeros(3), config=SimpleNamespace(chunk_rays=2))
    # Image 0: gaps 0, 0.5 / 2.5 and 1 / 1 -> median 20 %; image 2 has no points.
    assert heldout_error.depth_error(run, dataset, 0) == (
        "; at its 3 sparse points the rendered depth is 20.0% off the reconstruction's (median)")
    assert heldout_error.depth_error(run, dataset, 2) == ""


def test_heldout_error_perfect_field_scores_the_unseen_pixels_error_alone():
    heldout_error = load_script("heldout_error")
    error = np.array([1e-2, 1e-2, 1e-1, 1e-3])
    seen = np.array([True, True, False, True])
    assert heldout_error.perfect_field(error, seen, 0.5) == (
        "its rendered surface's dominant plane holds 50% of it, and 25.0% of its pixels meet that plane "
        "where no training photo sees it (PSNR 10.00 dB there): with every other pixel exact its PSNR would "
        "be 16.02 dB")
    assert heldout_error.perfect_field(error, np.ones(4, bool), 0.5).endswith("all of it seen in training")


@pytest.mark.parametrize("tolerance", ["0", "-0.1", "nan", "x"])
def test_heldout_error_refuses_a_plane_tolerance_that_is_no_positive_distance(tolerance):
    heldout_error = load_script("heldout_error")
    with pytest.raises(argparse.ArgumentTypeError, match=re.escape(repr(tolerance))):
        heldout_error.positive_distance(tolerance)
    assert heldout_error.positive_distance("0.05") == 0.05


def test_heldout_error_names_the_flag_when_the_plane_tolerance_is_refused():
    completed = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "heldout_error.py"), "run", "reconstruction",
         "--plane-tolerance", "0"], capture_output=True, text=True, cwd=ROOT)
    assert completed.returncode == 2
    assert "--plane-tolerance" in completed.stderr and "'0'" in completed.stderr
