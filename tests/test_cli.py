"""The command line: study listing, option checks and a quick study end to end."""

import json
import os
import subprocess
import sys

import jaxlib

from jaxest import cli, studies, xla_flags


def test_reproduce_help_lists_every_study(capsys):
    try:
        cli.main(["reproduce", "--help"])
    except SystemExit:
        pass
    text = capsys.readouterr().out
    for name in studies.STUDIES:
        assert name in text
    for option in ("--out", "--runs", "--seed", "--quick"):
        assert option in text


def test_unknown_study_is_refused():
    done = subprocess.run(
        [sys.executable, "-m", "jaxest", "reproduce", "nosuch"], capture_output=True, text=True
    )
    assert done.returncode != 0 and "invalid choice" in done.stderr


def test_filters_study_quick(tmp_path):
    # XLA flags of the user's own (here the suite's other one): the command keeps them and adds
    # the flag that compiles faster (jaxest.xla_flags), and the index records what ran
    env = {**os.environ, "XLA_FLAGS": " ".join(xla_flags.UNOPTIMISED_MACHINE_CODE)}
    done = subprocess.run(
        [sys.executable, "-m", "jaxest", "reproduce", "filters", "--quick", "--out", str(tmp_path)],
        capture_output=True, text=True, timeout=900, env=env,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "[filters]" in done.stderr  # the progress display
    summary = json.loads((tmp_path / "filters" / "summary.json").read_text())
    at = {(r["filter"], r["dtype"], r["delta"]): r["rel_error"] for r in summary["robustness"]}
    assert at[("svd_ekf", "float64", 1e-9)] < 1e-5 and at[("svd_improved", "float64", 1e-9)] < 1e-5
    assert at[("kf", "float64", 1e-9)] is None or at[("kf", "float64", 1e-9)] > 1e-2
    # the tuning demonstration: Q, R from a 10x wrong start, within 3 standard errors of the truth
    tuning = summary["tuning"]
    assert max(abs(z) for z in tuning["ml"]["z_scores"]) < 3.0
    assert tuning["rmse"]["ml"] < tuning["rmse"]["start"]
    assert tuning["rmse"]["supervised"] < tuning["rmse"]["start"]
    for name in ("robustness.png", "tuning.png", "tables.md"):
        assert (tmp_path / "filters" / name).stat().st_size > 0
    entry = json.loads((tmp_path / "index.json").read_text())["filters"]
    assert entry["dir"].endswith("filters")
    if jaxlib.__version__.startswith(xla_flags.MEASURED_JAXLIB):
        recorded = entry["xla_flags"].split()
        assert recorded == [*xla_flags.UNOPTIMISED_MACHINE_CODE, *xla_flags.FASTER_COMPILATION]


def test_progress_estimates_what_remains_from_the_steps_done():
    import io

    from jaxest.progress import Progress

    stream = io.StringIO()
    with Progress("study", total=4, stream=stream) as progress:
        assert progress.remaining(10.0) is None  # nothing done: no estimate
        progress.advance("one")
        assert progress.remaining(10.0) == 30.0  # 3 steps to go at 10 s each
        progress.advance("two", steps=3)
    lines = stream.getvalue().splitlines()
    assert "s left one" in lines[1] and "left" not in lines[0] and "left" not in lines[2]


def test_reproduce_estimates_from_the_last_run_in_the_same_mode(tmp_path):
    index = {
        "filters": {"seconds": 12.5, "dir": "x", "quick": True},
        "wiener": {"seconds": 40.0, "dir": "y", "quick": False},
        "old": {"seconds": 3.0, "dir": "z"},  # written before the mode was recorded
    }
    (tmp_path / "index.json").write_text(json.dumps(index))
    assert cli._seconds_by_study(tmp_path / "index.json", quick=True) == {"filters": 12.5}
    assert cli._seconds_by_study(tmp_path / "index.json", quick=False) == {"wiener": 40.0}
    assert cli._seconds_by_study(tmp_path / "missing.json", quick=True) == {}
    (tmp_path / "index.json").write_text("{not json")
    assert cli._seconds_by_study(tmp_path / "index.json", quick=True) == {}
