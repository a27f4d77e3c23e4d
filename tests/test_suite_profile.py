"""benchmarks/suite_profile.py: what it records of a test's compiling, and its summary."""

import jax
import jax.numpy as jnp
import pytest

from tests import benchmark_scripts

pytest_plugins = ["pytester"]

suite_profile = benchmark_scripts.load("suite_profile")


def test_a_jitted_program_and_an_operation_outside_jit_are_recorded_and_summarised(tmp_path):
    def cumulative_sine(x):
        return jnp.cumsum(jnp.sin(x))

    recorder = suite_profile._Recorder(tmp_path / "main.jsonl")
    jax.monitoring.register_event_duration_secs_listener(recorder)
    try:
        recorder.begin()
        # a program no other test compiles (its shape), and one operation run op by op
        jax.block_until_ready(jax.jit(cumulative_sine)(jnp.ones(37)))
        jax.block_until_ready(jnp.ones(41) * 3.0)
        recorder.end("tests/test_a.py::test_one", [])
        recorder.begin()  # a second test that compiles nothing
        recorder.end("tests/test_b.py::test_two", ["parametrize", "slow"])
    finally:
        jax.monitoring.unregister_event_duration_listener(recorder)
    records = suite_profile.read_records(tmp_path)
    assert [r["test"] for r in records] == [
        "tests/test_a.py::test_one",
        "tests/test_b.py::test_two",
    ]
    first, second = records
    assert first["counts"]["trace"] >= 1 and first["counts"]["compile"] >= 2
    assert first["counts"]["compile_small"] >= 1  # the multiplication's program
    assert first["seconds"]["compile"] >= first["seconds"]["compile_small"] > 0
    assert second["counts"] == {} and second["seconds"] == {}
    # the jitted function's three phases under its own name; the operation under another
    programs = first["programs"]
    assert programs["cumulative_sine"]["compiled"] == 1
    assert all(programs["cumulative_sine"][phase] > 0 for phase in ("trace", "lower", "compile"))
    assert (
        sum(split.get("compiled", 0) for split in programs.values()) == first["counts"]["compile"]
    )
    assert second["programs"] == {}
    summary = suite_profile.summarise(records, top=1)
    suite = summary["suite"]
    assert suite["tests"] == 2 and suite["programs_compiled"] == first["counts"]["compile"]
    phases = suite["trace_s"] + suite["lower_s"] + suite["compile_s"]
    assert suite["other_s"] == pytest.approx(suite["wall_s"] - phases)
    assert 0 < phases <= suite["wall_s"]
    assert [f["file"] for f in summary["files"]] == ["tests/test_a.py"]  # the slower, top=1
    split = summary["by_marker"]
    assert split["slow"]["tests"] == 1 and split["slow"]["programs_compiled"] == 0
    assert split["not slow"]["programs_compiled"] == suite["programs_compiled"]
    assert split["slow"]["wall_s"] + split["not slow"]["wall_s"] == pytest.approx(suite["wall_s"])
    assert summary["tests"][0]["test"] == "tests/test_a.py::test_one"
    (costliest,) = summary["programs"]  # top=1
    assert costliest["tests"] == 1
    assert costliest["total_s"] == pytest.approx(
        costliest["trace_s"] + costliest["lower_s"] + costliest["compile_s"]
    )
    every = suite_profile.summarise(records, top=100)["programs"]
    assert [row["total_s"] for row in every] == sorted(
        (row["total_s"] for row in every), reverse=True
    )
    assert sum(row["compiled"] for row in every) == suite["programs_compiled"]
    assert "cumulative_sine" in [row["program"] for row in every]


def test_a_program_is_named_by_its_function_in_every_phase():
    assert suite_profile.program_name("jit(loss)") == "loss"
    assert suite_profile.program_name("loss") == "loss"
    assert suite_profile.program_name("jit(jit(f))") == "jit(f)"


def test_an_empty_directory_is_an_error_naming_it(tmp_path):
    with pytest.raises(ValueError, match="^directory: no test records"):
        suite_profile.read_records(tmp_path)


def test_the_plugin_writes_a_record_per_test_where_it_runs(pytester, tmp_path):
    pytester.makepyfile(
        test_two="""
        import jax, jax.numpy as jnp
        import pytest

        @pytest.mark.slow
        def test_compiles():
            jax.block_until_ready(jax.jit(lambda x: jnp.cos(x) * 2)(jnp.ones(43)))

        def test_compiles_nothing():
            assert True
        """
    )
    directory = tmp_path / "profile"
    result = pytester.runpytest_inprocess("-p", "suite_profile", f"--suite-profile={directory}")
    result.assert_outcomes(passed=2)
    records = suite_profile.read_records(directory)
    assert [r["test"] for r in records] == [
        "test_two.py::test_compiles",
        "test_two.py::test_compiles_nothing",
    ]
    assert records[0]["counts"]["compile"] >= 1 and records[1]["counts"] == {}
    assert [r["markers"] for r in records] == [["slow"], []]
    assert suite_profile._recorder is None  # the listener goes with the session
