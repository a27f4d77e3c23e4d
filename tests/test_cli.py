"""The command line: study listing, option checks and a quick study end to end."""

import json
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import jaxlib
import pytest

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


@pytest.mark.parametrize(
    "argv,message",
    [
        (["nosuch"], "invalid choice"),
        (["filters", "--jobs", "0"], "argument --jobs: must be at least 1, got 0"),
        (["filters", "--runs", "-3"], "argument --runs: must be at least 1, got -3"),
        (["filters", "--jobs", "two"], "argument --jobs: expected a whole number, got 'two'"),
        # an option for a study not chosen was ignored without a word
        (["wiener", "--b747-printed"], "--b747-printed: only the adaptive study reads it"),
        (["wiener", "--data", "."], "--data: only the svd-ekf study reads it"),
    ],
)
def test_usage_errors_exit_with_2_and_the_usage(capsys, argv, message):
    """Every mistake in the command line, argparse's or ours, exits with 2 and prints the usage
    (``--jobs 0`` and an option for a study not chosen exited with 1 and no usage line)."""
    with pytest.raises(SystemExit) as exit_:
        cli.main(["reproduce", *argv])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.startswith("usage:") and message in err, err


def test_an_output_folder_that_cannot_be_made_is_named(tmp_path):
    (tmp_path / "file").write_text("")  # was a NotADirectoryError traceback
    with pytest.raises(SystemExit, match="^--out: cannot create .*Not a directory"):
        cli.main(["reproduce", "filters", "--quick", "--out", str(tmp_path / "file" / "sub")])
    with pytest.raises(SystemExit, match="^--out: .*file is a file, not a directory$"):
        cli.main(["reproduce", "filters", "--quick", "--out", str(tmp_path / "file")])


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs Linux's /proc")
def test_an_output_folder_that_cannot_be_written_and_bad_data_are_named(tmp_path):
    """A PermissionError traceback from inside the first study; --data that is not a directory
    (a ValueError traceback) or lacks the svd-ekf study's records (found after its simulated
    part, 22 s into --quick, with a traceback and a partial folder)."""
    with pytest.raises(SystemExit, match="^--out: cannot write in /proc"):
        cli.main(["reproduce", "wiener", "--quick", "--out", "/proc"])
    out = str(tmp_path / "out")
    with pytest.raises(SystemExit, match="^--data: .*nowhere is not a directory"):
        cli.main(
            ["reproduce", "svd-ekf", "--quick", "--out", out, "--data", str(tmp_path / "nowhere")]
        )
    with pytest.raises(SystemExit, match="^--data: .* lacks fAttasElv1_pqrDot.asc, "):
        cli.main(["reproduce", "svd-ekf", "--quick", "--out", out, "--data", str(tmp_path)])


@pytest.mark.slow
def test_filters_study_quick_beside_another(tmp_path):
    # XLA flags of the user's own (here the suite's other two): the command keeps them and adds
    # the flag that compiles faster (jaxest.xla_flags), and the index records what ran
    own = xla_flags.UNOPTIMISED_MACHINE_CODE + xla_flags.SERIAL_CODEGEN
    env = {**os.environ, "XLA_FLAGS": " ".join(own)}
    done = subprocess.run(
        [sys.executable, "-m", "jaxest", "reproduce", "wiener", "filters", "--quick", "--jobs", "2",
         "--out", str(tmp_path)],
        capture_output=True, text=True, timeout=900, env=env,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "[filters]" in done.stderr and "[wiener]" in done.stderr  # the progress display
    assert "beside" in done.stderr  # the two ran at once
    assert (tmp_path / "wiener" / "summary.json").stat().st_size > 0
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
    index = json.loads((tmp_path / "index.json").read_text())
    assert sorted(index) == ["filters", "wiener"] and not list(tmp_path.glob(".index-*"))
    entry = index["filters"]
    assert entry["dir"].endswith("filters") and entry["jobs"] == 2 and entry["quick"]
    if jaxlib.__version__.startswith(xla_flags.MEASURED_JAXLIB):
        recorded = entry["xla_flags"].split()
        assert recorded == [*own, *xla_flags.FASTER_COMPILATION]


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


def test_progress_weighs_steps_by_their_expected_cost():
    import io

    from jaxest.progress import Progress

    stream = io.StringIO()
    with Progress("study", total=3, stream=stream, weights=[1, 1, 6]) as progress:
        progress.advance("cheap")
        assert progress.remaining(10.0) == 70.0  # 7 units to go at 10 s each, not 2 steps
        assert progress.fraction() == 0.125
    assert "[###---------------------] 1/3" in stream.getvalue()  # the bar by cost
    for weights in ([1, 2], [1, 0, 2]):
        with pytest.raises(ValueError, match="^weights: 3 positive costs"):
            Progress("study", total=3, stream=stream, weights=weights)


def test_reproduce_estimates_from_the_last_run_in_the_same_mode(tmp_path):
    index = {
        "filters": {"seconds": 12.5, "dir": "x", "quick": True},
        "wiener": {"seconds": 40.0, "dir": "y", "quick": False},
        "old": {"seconds": 3.0, "dir": "z"},  # written before the mode was recorded
    }
    (tmp_path / "index.json").write_text(json.dumps(index))
    index = cli._read_index(tmp_path / "index.json")
    assert cli._seconds_by_study(index, quick=True, jobs=1) == {"filters": 12.5}
    assert cli._seconds_by_study(index, quick=False, jobs=1) == {"wiener": 40.0}
    assert cli._seconds_by_study(index, quick=False, jobs=2) == {}
    assert cli._read_index(tmp_path / "missing.json") == {}
    (tmp_path / "index.json").write_text("{not json")
    assert cli._read_index(tmp_path / "index.json") == {}


def test_jobs_start_the_longest_first_and_the_timed_studies_alone_at_the_end():
    seconds = {"svd-ekf": 250.0, "sigma-point": 100.0, "network": 50.0, "filters": 30.0,
               "parallel": 140.0, "smf-fdi": 17.0}  # fmt: skip
    given = ["filters", "smf-fdi", "svd-ekf", "parallel", "network", "sigma-point"]
    order = cli._start_order(given, seconds)
    assert order == ["svd-ekf", "sigma-point", "network", "filters", "smf-fdi", "parallel"]
    # without a time for every untimed study: longest first by the typical times
    assert cli._start_order(["wiener", "filters", "adaptive", "smf-fdi", "svd-ekf"], {}) == [
        "svd-ekf", "adaptive", "filters", "wiener", "smf-fdi"]  # fmt: skip
    # two at a time: svd-ekf | sigma-point, network, filters (180 s); then 17 + 140 s alone
    assert cli._seconds_to_go({}, order, seconds, jobs=2) == 250.0 + 157.0
    assert cli._seconds_to_go({}, order, seconds, jobs=1) == sum(seconds.values())
    # svd-ekf has run 200 of its 250 s; filters takes the free slot
    assert cli._seconds_to_go({"svd-ekf": 200.0}, ["filters"], seconds, jobs=2) == 50.0
    assert cli._seconds_to_go({"parallel": 100.0}, [], seconds, jobs=2) == 40.0
    assert cli._seconds_to_go({}, ["wiener"], seconds, jobs=2) is None  # never timed


def test_a_first_run_of_every_study_starts_the_longest_first():
    """A fresh clone's ``reproduce all --jobs 2``: by the typical times, longest first ends sooner
    than the listed order, which ran the other five studies after one another past svd-ekf."""
    typical = studies.TYPICAL_SECONDS
    assert set(typical) == set(studies.STUDIES)
    names = list(studies.STUDIES)
    listed = [n for n in names if not cli._timed(n)] + [n for n in names if cli._timed(n)]
    first_run = cli._start_order(names, {})
    assert first_run[0] == "svd-ekf"
    assert cli._seconds_to_go({}, first_run, typical, jobs=2) < cli._seconds_to_go(
        {}, listed, typical, jobs=2
    )


def test_worker_command_forwards_every_option(tmp_path):
    argv = ["reproduce", "svd-ekf", "--out", str(tmp_path), "--runs", "3", "--seed", "7",
            "--quick", "--data", str(tmp_path / "flight"), "--b747-printed", "--jobs", "2"]  # fmt: skip
    args = cli._parser().parse_args(argv)
    command = cli._worker_command("svd-ekf", args, tmp_path / "entry.json")
    assert command[:3] == [sys.executable, "-m", "jaxest"]
    worker = cli._parser().parse_args(command[3:])
    assert worker.worker == tmp_path / "entry.json"
    assert {**vars(worker), "worker": None} == vars(args)


def test_a_study_named_twice_runs_once(tmp_path, monkeypatch):
    ran = []  # a stand-in for the study: `reproduce wiener wiener` ran it twice
    monkeypatch.setattr(
        studies, "load",
        lambda name: SimpleNamespace(DESCRIPTION=name, run=lambda *a, **k: ran.append(name)),
    )  # fmt: skip
    cli.main(["reproduce", "wiener", "filters", "wiener", "--out", str(tmp_path)])
    assert ran == ["wiener", "filters"]


def test_after_a_failed_study_no_other_starts(tmp_path, monkeypatch, capsys):
    # stand-ins for the study processes: wiener fails, filters finishes half a second after it,
    # network would leave a mark. The folder holds an earlier run's wiener, network and svd-ekf.
    failing = tmp_path / "wiener.failing"
    scripts = {
        "wiener": f"import sys; print('boom', file=sys.stderr); open({str(failing)!r}, 'w');"
        " sys.exit(3)",
        "filters": f"import json, os, sys, time\nwhile not os.path.exists({str(failing)!r}):"
        " time.sleep(0.05)\ntime.sleep(0.5)\n"
        "open(sys.argv[1], 'w').write(json.dumps({'filters': {'seconds': 1.0}}))",
        "network": "import sys; open(sys.argv[1] + '.started', 'w')",
    }
    monkeypatch.setattr(
        cli, "_worker_command",
        lambda name, args, entry: [sys.executable, "-c", scripts[name], str(entry)],
    )  # fmt: skip
    earlier = {name: {"seconds": 9.0} for name in ("wiener", "network", "svd-ekf")}
    (tmp_path / "index.json").write_text(json.dumps(earlier))
    # (their entries have no mode, so the start order is by these: wiener and filters, then network)
    monkeypatch.setattr(studies, "TYPICAL_SECONDS", {"wiener": 3.0, "filters": 2.0, "network": 1.0})
    with pytest.raises(SystemExit, match="wiener failed"):
        cli.main(
            ["reproduce", "wiener", "filters", "network", "--jobs", "2", "--out", str(tmp_path)]
        )
    err = capsys.readouterr().err
    assert "[wiener] boom" in err and "wiener: failed (exit code 3)" in err
    assert not list(tmp_path.glob("*.started"))
    # the index: the study that finished, and the earlier ones not redone; not the failed one
    index = json.loads((tmp_path / "index.json").read_text())
    assert index == {"filters": {"seconds": 1.0}, "network": {"seconds": 9.0},
                     "svd-ekf": {"seconds": 9.0}}  # fmt: skip


def test_the_timed_studies_run_alone(tmp_path, monkeypatch):
    # stand-ins for the study processes, each noting when it ran and the XLA flags it was given
    script = (
        "import json, os, sys, time\nname, entry = sys.argv[1:]\nstart = time.time()\n"
        "time.sleep(1.0)\nopen(entry, 'w').write(json.dumps({name: {'seconds': 1.0, "
        "'ran': [start, time.time()], 'xla_flags': os.environ.get('XLA_FLAGS', '')}}))"
    )
    monkeypatch.setattr(jaxlib, "__version__", xla_flags.MEASURED_JAXLIB + "2")
    monkeypatch.setenv("XLA_FLAGS", "--xla_backend_optimization_level=2")  # the user's own
    monkeypatch.setattr(
        cli, "_worker_command",
        lambda name, args, entry: [sys.executable, "-c", script, name, str(entry)],
    )  # fmt: skip
    names = ["smf-fdi", "wiener", "parallel", "filters"]
    args = cli._parser().parse_args(["reproduce", *names, "--jobs", "2", "--out", str(tmp_path)])
    index, failed = cli._run_in_processes(names, args, {})
    assert not failed
    ran = {name: entry["ran"] for name, entry in index.items()}
    overlap = lambda a, b: ran[a][0] < ran[b][1] and ran[b][0] < ran[a][1]
    assert overlap("wiener", "filters")
    assert not any(overlap(a, b) for a in ("smf-fdi", "parallel") for b in names if b != a)
    # the studies beside another compile machine code in one piece; those alone as the user has it
    flags = {name: entry["xla_flags"].split() for name, entry in index.items()}
    user = ["--xla_backend_optimization_level=2"]
    assert flags["wiener"] == flags["filters"] == [*user, *xla_flags.SERIAL_CODEGEN]
    assert flags["parallel"] == user
    # and the study that shards its runs over the devices gets one per core
    assert flags["smf-fdi"] == [*user, *xla_flags.cpu_devices()]
    assert os.environ["XLA_FLAGS"].split() == user  # this process's own are left as they were
