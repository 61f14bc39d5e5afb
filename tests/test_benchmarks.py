"""The benchmark scripts run end to end at their smallest settings and write the JSON they document."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import REAL_DEV, stress_scene

ROOT = Path(__file__).resolve().parents[1]


def _run(script: str, out: Path, *args: str) -> dict:
    """Run benchmarks/<script> with --json out and the given arguments; its JSON report."""
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), *args, "--json", str(out)],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert f"written {out}" in done.stdout
    return json.loads(out.read_text())


def test_latency_times_every_stage_at_both_sizes(tmp_path):
    report = _run("latency.py", tmp_path / "latency.json", "--frames", "1", "--repeat", "2", "--threads", "1",
                  "--no-opencv")
    assert [run["size"] for run in report["runs"]] == ["640x480", "2000x1500"]
    for run in report["runs"]:
        stages = run["stages"]
        assert {"total", "best_total", "network", "peaks", "refine"} <= set(stages)
        assert 0 < stages["best_total"]["median_ms"] <= stages["total"]["p90_ms"]
        assert stages["network"]["median_ms"] < stages["total"]["median_ms"]
    assert report["cold_start_ms"]["default"] > 0
    boardless = report["boardless_ms"]
    assert set(boardless) == {"default", "fast check"}
    assert all(set(v) == {"640x480", "2000x1500"} and min(v.values()) > 0 for v in boardless.values())
    rss = report["peak_rss_mb"]["default"]
    assert set(rss) == {"640x480", "2000x1500"} and min(rss.values()) > 0


def test_latency_models_name_one_model_a_cascade_or_the_default():
    """--models entries: a lone name runs that model on every pass, COARSE+FULL a cascade of two,
    'default' the default detector."""
    import ccdn

    sys.path.insert(0, str(ROOT / "benchmarks"))
    from latency import _detector

    assert _detector("fine", 1).models == "fine"
    assert _detector("fast-int8+fine-int8", 1).models == "fast-int8+fine-int8"
    assert _detector("default", 1).models == ccdn.Detector(threads=1).models


# the fast check looks only for squares of 7 px or more on the halved frame: the first clean render's are
# 6.7 px there (it finds nothing, as promised); the second's are 9.9 px
@pytest.mark.parametrize("check", [[], ["--fast-check", "--skip", "1"]])
def test_stress_counts_a_clean_render_whole_and_a_boardless_one_empty(tmp_path, check):
    report = _run("stress.py", tmp_path / "stress.json", "--per-subset", "1", "--subsets", "clean", "no-board",
                  "--detectors", "ccdn", *check)
    assert ("fast check" in report["config"]["detectors"]["ccdn"]) == bool(check)
    clean, empty = (report["subsets"][name]["detectors"]["ccdn"] for name in ("clean", "no-board"))
    assert clean["labels"] > 0 and clean["missed_pct"] == 0 and clean["false_positives"] == 0
    assert clean["accuracy_px"] < 0.1
    assert empty["labels"] == 0 and empty["false_positives"] == 0
    widths = clean["missed_by_width"]  # a calm render's squares are all wide
    assert widths[">= 6 px"] == {"labels": clean["labels"], "missed_pct": 0.0}
    assert widths["0-4 px"]["labels"] == widths["4-6 px"]["labels"] == 0
    assert clean["missed_by_situation"]["open"] == {"labels": clean["labels"], "missed_pct": 0.0}  # a calm board in view


def test_square_widths_tell_a_steep_views_slivers_from_a_calm_boards_squares():
    """The stress set's extreme-pose render 7100061 is a board seen almost edge-on: 2-3 px across its
    squares (measured), though its corners lie 4.6-13 px apart; a calm board's squares are as wide as
    its corners are apart."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from stress import square_widths

    sliver = square_widths(stress_scene("extreme-pose", 7_100_061))
    assert len(sliver) == 42 and sliver.max() < 3.5
    calm = stress_scene("clean", 7_000_004)
    apart = np.linalg.norm(calm.corners[:, None] - calm.corners[None], axis=2)
    np.fill_diagonal(apart, np.inf)
    assert np.allclose(square_widths(calm), apart.min(1), rtol=0.1)


def test_label_situations_tell_plain_corners_from_hidden_neighbours_pieces_and_slivers():
    """Two-boards render 7120536: a whole 10 x 10 board in front of an 11 x 4 one, of which 13 corners
    show, in a piece of 5 and a piece of 8 (4 of those beside a corner the front board hides);
    occluded render 7140745: an occluder cuts a piece of 4 corners off the rest and hides the
    neighbours of 6 more; the sliver of extreme-pose render 7100061 has squares under 4 px across
    (measured: 2-3 px); a calm board's corners are all in plain view."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from stress import SITUATIONS, label_situations, square_widths

    def counts(subset: str, seed: int) -> list[list[int]]:
        scene = stress_scene(subset, seed)
        situation = label_situations(scene, square_widths(scene))
        return [np.bincount(situation[scene.board_index == b], minlength=len(SITUATIONS)).tolist()
                for b in range(len(scene.boards))]

    assert SITUATIONS[0] == "open"
    assert counts("two-boards", 7_120_536) == [[4, 4, 5, 0], [100, 0, 0, 0]]
    assert counts("occluded", 7_140_745) == [[12, 6, 4, 0]]
    assert counts("extreme-pose", 7_100_061) == [[0, 0, 0, 42]]
    assert counts("clean", 7_000_004) == [[49, 0, 0, 0]]


def test_accuracy_reports_the_paper_metrics_per_group(tmp_path):
    report = _run("accuracy.py", tmp_path / "accuracy.json", "--synthetic", "3", "--no-real-dev")
    rendered = [row for row in report["per_image"] if row["group"] == "synthetic"]
    assert len(rendered) == 3 and len(report["per_image"]) == 4  # and one render without a board
    assert all(row["hits"] + row["missed"] == row["labels"] for row in rendered)
    group = report["groups"]["synthetic"]
    assert group["labels"] == sum(row["labels"] for row in rendered) > 0
    assert abs(group["missed_pct"] - 100 * sum(row["missed"] for row in rendered) / group["labels"]) < 1e-9


@pytest.mark.skipif(not (REAL_DEV / "labels.json").is_file(), reason="../shared/data/real-dev not present")
def test_perturbed_moves_the_labels_with_the_photo(tmp_path):
    report = _run("perturbed.py", tmp_path / "perturbed.json", "--limit", "2", "--perturbations", "identity", "rot90",
                  "half")
    groups = report["groups"]
    assert list(groups) == ["identity", "rot90", "half"]
    for group in groups.values():  # labels rotated or halved with the photo still meet the corners
        assert group["images"] == 2 and group["labels"] == groups["identity"]["labels"] > 0
        assert group["missed_pct"] < 5 and group["boards_recovered"] == 2 and group["accuracy_px"] < 0.3
