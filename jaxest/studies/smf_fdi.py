"""Study ``smf-fdi``: the ellipsoidal set-membership filter and guaranteed sensor fault detection
and isolation on the Duffing system (Chai & Sun 2007, §4, figs 1-3, tables 2-3; docs/papers/smf.md).

Protocol: paper steps k = 1..100; sensor 1 carries a bias 0.03 + 0.01 L from k = 50 on, for
L = 0, 1, 2, plus a fault-free scenario; noise uniform in its box; the same noise draws (one key per
run) serve every scenario, so the runs coincide before the fault. Every run, scenario and filter
(detection filter, the single-sensor filters of both isolation banks, the EKF baseline) runs in
one program under ``vmap``, each distinct set-membership run once (:func:`run_bank_scenarios`):
the steps before the fault once per filter, and the sensor-2 filter, which never sees the
fault, once over all four scenarios. The missed rates move with the seed, so the study also
repeats the Monte Carlo for ``SEEDS`` consecutive seeds and reports their spread.

EKF + chi-square baseline: Q, R are the variances of the uniform noise (w^2/3, the primary rule)
or (w/3)^2 (the box read as +-3 sigma); the test alarms when the normalised innovation squared
exceeds its chi-square(2) quantile at significance ``SIGNIFICANCE`` per step.

The bank helpers work for any number m of sensors and any system: :func:`filter_bank` (the
distinct filters of detection and both isolation methods), :func:`run_bank`,
:func:`run_bank_scenarios` (:func:`scenario_plan`), :func:`fdi_scores`, and for a Monte Carlo
of one fault :func:`bank_monte_carlo_function` and
:func:`bank_rates` (the three-sensor example of :mod:`jaxest.systems.pendulum`); the paper's
study uses ``filter_bank(2)``.
"""

from __future__ import annotations

import functools
import time
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding, PartitionSpec

from jaxest import xla_flags
from jaxest._priors import Gaussian
from jaxest._run import SaveAt, run as run_estimator
from jaxest.filters import EKF
from jaxest.filters.common import covariance_predict
from jaxest.models import NonlinearGaussian
from jaxest.montecarlo import RUNS_AXIS, default_mesh
from jaxest.progress import Progress
from jaxest.report import markdown_table, write_json
from jaxest.setmembership import fdi
from jaxest.setmembership.ellipsoid import is_positive_definite
from jaxest.setmembership.smf import SetMembershipFilter, SMFResult
from jaxest.systems import duffing

DESCRIPTION = (
    "ellipsoidal set-membership filter and guaranteed sensor FDI (Duffing, Chai & Sun 2007)"
)
NAME = "smf-fdi"
#: its tables report wall times (the 200-run study after compiling)
TIMED = True
#: its Monte Carlo shards the runs over the devices (:func:`shard_runs`): ``reproduce --jobs N``
#: runs it in a process of its own with one CPU device per core
RUNS_ACROSS_CORES = True
LEVELS = (0, 1, 2)
DEFAULT_RUNS = 200
SEEDS = 5
SIGNIFICANCE = 0.01
VARIANCE_RULES = {"w^2/3": lambda w: w**2 / 3, "(w/3)^2": lambda w: (w / 3) ** 2}


class FilterBank(NamedTuple):
    """The distinct SMFs of guaranteed FDI with m sensors: ``masks[f]`` the sensors filter f
    sees, ``names[f]`` a label, ``detection`` the row of the detection filter (every sensor) and
    ``isolation[method]`` the rows (m,) of that method's bank (filter i of method 1 sees sensor i
    only, of method 2 every sensor but i; :func:`jaxest.setmembership.fdi.bank_masks`)."""

    masks: np.ndarray
    names: tuple[str, ...]
    detection: int
    isolation: dict[int, np.ndarray]


def _filter_name(mask: np.ndarray) -> str:
    """The label of a bank's filter: all sensors, sensor i or all but sensor i (1-based)."""
    if mask.all():
        return "all sensors"
    if mask.sum() == 1:
        return f"sensor {np.argmax(mask) + 1}"
    return f"all but sensor {np.argmin(mask) + 1}"


def filter_bank(m: int) -> FilterBank:
    """The detection filter and both isolation banks for ``m`` >= 2 sensors, each distinct filter
    once: 1 + 2m filters, or 3 when m = 2, where method 2's filter i (every sensor but i) is
    method 1's filter of the other sensor."""
    if not isinstance(m, int | np.integer) or m < 2:
        raise ValueError(f"m: expected an integer number of sensors >= 2, got {m!r}")
    masks = [np.ones(m, bool)]
    isolation = {}
    for method in (1, 2):
        rows = []
        for mask in fdi.bank_masks(m, method):
            found = [f for f, seen in enumerate(masks) if np.array_equal(seen, mask)]
            if not found:
                masks.append(mask)
            rows.append(found[0] if found else len(masks) - 1)
        isolation[method] = np.asarray(rows)
    masks = np.stack(masks)
    return FilterBank(masks, tuple(map(_filter_name, masks)), 0, isolation)


def run_bank(model, prior, ys: jnp.ndarray, masks: np.ndarray) -> SMFResult:
    """The SMF over one run ``ys`` (T, m) for every row of ``masks`` (F, m), fed only the
    sensors of that row (:func:`~jaxest.setmembership.fdi.sensor_subset`); one ``vmap``, so the
    result's arrays gain a leading filter axis (F, T, ...)."""
    smf = SetMembershipFilter()
    one = lambda mask: run_estimator(smf, model, fdi.sensor_subset(ys, mask), prior=prior)
    return jax.vmap(one)(jnp.asarray(masks))


def bank_contains(result: SMFResult, states: jnp.ndarray) -> jnp.ndarray:
    """(F, T): whether each filter's set of a :func:`run_bank` result holds ``states`` (T, n)."""
    return jax.vmap(lambda one: one.contains(states))(result)


def isolation_score(
    inconsistent, bank: FilterBank, method: int, faulty: int, fault_start: int, reading="same_step"
) -> dict:
    """:func:`~jaxest.setmembership.fdi.score` of one isolation method over runs, from the bank's
    flags ``inconsistent`` (runs, F, T), with the fault on sensor ``faulty`` (0-based) from step
    ``fault_start``: a decision naming the faulty sensor is an alarm, one naming another sensor a
    false alarm. ``reading``: method 2's (:func:`~jaxest.setmembership.fdi.isolation_decisions`)."""
    m = bank.masks.shape[-1]
    if not 0 <= faulty < m:
        raise ValueError(f"faulty: expected a sensor index in [0, {m}), got {faulty}")
    bank_flags = np.asarray(inconsistent)[:, bank.isolation[method]]
    decisions = np.asarray(fdi.isolation_decisions(bank_flags, method, reading))  # (runs, T, m)
    others = np.delete(decisions, faulty, axis=-1)
    return fdi.score(decisions[..., faulty], fault_start, wrong=np.any(others, axis=-1))


def fdi_scores(inconsistent, bank: FilterBank, faulty: int, fault_start: int, reading="same_step"):
    """Scores of detection and both isolation methods (method 2 in ``reading``) over runs, from
    the flags ``inconsistent`` (runs, F, T) of every filter of ``bank``."""
    return {
        "detection": fdi.score(np.asarray(inconsistent)[:, bank.detection], fault_start),
        **{
            f"isolation_method{method}": isolation_score(
                inconsistent, bank, method, faulty, fault_start, reading
            )
            for method in (1, 2)
        },
    }


class ScenarioPlan(NamedTuple):
    """The distinct runs of a bank's filters over scenarios (:func:`scenario_plan`): every
    filter's measurements agree in all scenarios before step ``split``; from it on, ``pairs``
    (P, 2) lists the distinct runs as (filter, scenario), and ``index[s, f]`` is the pair whose
    run is filter f's in scenario s."""

    split: int
    pairs: np.ndarray
    index: np.ndarray


def scenario_plan(biases, masks: np.ndarray) -> ScenarioPlan:
    """The runs a bank (``masks`` (F, m)) needs over scenarios that differ only by the sensor
    biases (S, T, m) added to the same noisy measurements (one key per run serves every
    scenario). Filter f sees the same measurements in two scenarios wherever their biases on
    the sensors it sees agree: in all of them before the first step where any bias on a seen
    sensor differs, and throughout where none ever does (the sensor-2 filter when only sensor 1
    is faulty). ``biases`` must be concrete: the plan is fixed when the program is traced."""
    biases, masks = np.asarray(biases), np.asarray(masks, bool)
    seen = np.where(masks[None, :, None, :], biases[:, None], 0.0)  # (S, F, T, m)
    differs = np.any(seen != seen[:1], axis=(0, 1, 3))  # (T,)
    split = int(np.argmax(differs)) if differs.any() else biases.shape[1]
    pairs, index = [], np.zeros(seen.shape[:2], int)
    for f in range(len(masks)):
        for s in range(len(biases)):
            same = [
                p for p, (g, r) in enumerate(pairs) if g == f and (seen[r, f] == seen[s, f]).all()
            ]
            if not same:
                pairs.append((f, s))
            index[s, f] = same[0] if same else len(pairs) - 1
    return ScenarioPlan(split, np.asarray(pairs, int).reshape(-1, 2), index)


def run_bank_scenarios(model, prior, states, ys, biases, masks: np.ndarray) -> tuple:
    """``(inconsistent, contains, unbounded)``, each (S, F, T): the SMF of every row of ``masks``
    (F, m: the sensors each filter sees) over every scenario's truth ``states`` (S, T, n) and
    measurements ``ys`` (S, T, m), the scenarios differing only by ``biases`` (S, T, m,
    concrete). The same as :func:`run_bank` and :func:`bank_contains` per scenario, but each
    distinct run is computed once (:func:`scenario_plan`): the steps all scenarios share once
    per filter, then each distinct rest, resumed where its filter left off."""
    plan = scenario_plan(biases, masks)
    split, (filters, scenarios) = plan.split, plan.pairs.T
    masks = jnp.asarray(masks)
    smf = SetMembershipFilter()
    kept = SaveAt(fields=("center", "shape", "status"))  # what the flags need of each step

    def run_one(mask, ys, states, start, k0):
        subset = fdi.sensor_subset(ys, mask)
        start_from = {"prior": prior} if start is None else {"state": start}
        result = run_estimator(smf, model, subset, **start_from, k0=k0, save=kept)
        flags = result.inconsistent, result.contains(states), result.unbounded
        return flags, result.final_state

    parts, start = [], None
    if split > 0:  # every filter once over the shared steps, as in scenario 0
        shared, final = jax.vmap(run_one, (0, None, None, None, None))(
            masks, ys[0, :split], states[0, :split], None, 0
        )
        parts.append(jax.tree.map(lambda a: jnp.broadcast_to(a, (len(ys), *a.shape)), shared))
        start = jax.tree.map(lambda a: a[filters], final)
    if split < ys.shape[1]:  # each distinct rest once
        rest, _ = jax.vmap(run_one, (0, 0, 0, 0, None))(
            masks[filters], ys[scenarios, split:], states[scenarios, split:], start, split
        )
        parts.append(jax.tree.map(lambda a: a[plan.index], rest))
    return tuple(jnp.concatenate(segments, axis=-1) for segments in zip(*parts, strict=True))


def bank_monte_carlo_function(model, prior, simulate, fault_bias, bank: FilterBank):
    """A jitted ``keys -> (inconsistent, contains)``, each (runs, 2, F, T): every filter of
    ``bank`` over a fault-free run (scenario 0) and the same run with ``fault_bias`` (T, m,
    concrete) added to the measurements (scenario 1), the same noise draws in both;
    ``simulate(key, bias) -> (states, ys)``, ``prior`` the set at the first measurement. Runs
    are vmapped (:func:`batched_over_runs`); each distinct filter run is computed once
    (:func:`run_bank_scenarios`), which relies on ``simulate`` adding ``bias`` to the
    measurements alone: the same states, and the same measurements wherever the bias is 0."""
    biases = np.stack([np.zeros_like(fault_bias), fault_bias])

    def one_run(key):
        states, ys = jax.vmap(simulate, (None, 0))(key, jnp.asarray(biases))
        return run_bank_scenarios(model, prior, states, ys, biases, bank.masks)[:2]

    return batched_over_runs(one_run)


def bank_rates(inconsistent, bank: FilterBank, faulty: int, fault_start: int) -> dict:
    """Per method (method 2 in both readings), from the flags (runs, 2, F, T) of
    :func:`bank_monte_carlo_function`: ``rate``, the share of faulty runs where the fault was
    detected (the faulty sensor isolated) in [fault_start, T]; ``false_alarm_rate``, of faulty
    runs with an alarm before the fault or naming a healthy sensor; ``fault_free_alarm_rate``, of
    fault-free runs with any alarm; ``mean_delay`` in steps."""
    inconsistent = np.asarray(inconsistent)
    never = inconsistent.shape[-1] + 1  # on fault-free runs every alarm is a false alarm
    scores = []
    for flags, start in ((inconsistent[:, 1], fault_start), (inconsistent[:, 0], never)):
        by_method = fdi_scores(flags, bank, faulty, start, "same_step")
        by_method["isolation_method2_same_step"] = by_method.pop("isolation_method2")
        by_method["isolation_method2_by_step"] = isolation_score(
            flags, bank, 2, faulty, start, "by_step"
        )
        scores.append(by_method)
    faulty_runs, fault_free = scores
    return {
        key: {
            "rate": 1.0 - f["missed_rate"],
            "false_alarm_rate": f["false_alarm_rate"],
            "fault_free_alarm_rate": fault_free[key]["false_alarm_rate"],
            "mean_delay": f["mean_delay"],
        }
        for key, f in faulty_runs.items()
    }


#: the paper's two sensors: the detection filter and the isolation filters (sensor 1 only,
#: sensor 2 only), which serve both methods
BANK = filter_bank(2)
PAPER = {
    "detection": {
        "0": {"missed_rate": 0.755, "min_delay": 0, "max_delay": 1, "mean_delay": 0.02},
        "1": {"missed_rate": 0.0, "min_delay": 0, "max_delay": 33, "mean_delay": 2.31},
        "2": {"missed_rate": 0.0, "min_delay": 0, "max_delay": 6, "mean_delay": 0.05},
    },
    "isolation": {
        "0": {"missed_rate": 0.84, "min_delay": 0, "max_delay": 4, "mean_delay": 0.19},
        "1": {"missed_rate": 0.46, "min_delay": 0, "max_delay": 2, "mean_delay": 0.05},
        "2": {"missed_rate": 0.09, "min_delay": 0, "max_delay": 0, "mean_delay": 0.0},
    },
    "false_alarm_rate": 0.0,
    "ekf_chi2_false_alarm_rate": 1.0,
}


def first_prior(closed_form_bound: bool = False):
    """E_{1|0}: the paper's E_0 (at k = 0, no measurement) carried to the first measurement."""
    return SetMembershipFilter().predict(duffing.model(closed_form_bound), duffing.prior())


def scenario_biases() -> jnp.ndarray:
    """(1 + len(LEVELS), N, m): the fault-free scenario, then L = 0, 1, 2."""
    faults = [duffing.sensor_bias(L) for L in LEVELS]
    return jnp.stack([jnp.zeros_like(faults[0]), *faults])


def simulate_run(key, L):
    """Truth and measurements of one run with fault level L (``None``: no fault)."""
    bias = duffing.sensor_bias(0)
    return duffing.simulate(key, jnp.zeros_like(bias) if L is None else duffing.sensor_bias(L))


def ekf_model(rule: str) -> NonlinearGaussian:
    variance = VARIANCE_RULES[rule]
    Q = jnp.eye(2) * variance(duffing.PROCESS_BOUND)
    R = jnp.eye(2) * variance(duffing.MEASUREMENT_BOUND)
    return NonlinearGaussian(f=duffing.Duffing(), h=duffing.observe, Q=Q, R=R)


def ekf_prior(model: NonlinearGaussian) -> Gaussian:
    """N(x0_hat, 0.01 I) at k = 0 predicted to the first measurement."""
    x0 = jnp.asarray(duffing.X0)
    return Gaussian(*covariance_predict(model, x0, duffing.P0_SCALE * jnp.eye(2), None, 0))


def _one_run(key, biases, closed_form_bound=False):
    """Every scenario and filter of one run: SMF flags (S, F, T) and EKF alarms (S, rules, T)."""
    model = duffing.model(closed_form_bound)
    prior = first_prior(closed_form_bound)
    threshold = fdi.chi_square_threshold(2, SIGNIFICANCE)
    ekfs = [(ekf_model(rule), ekf_prior(ekf_model(rule))) for rule in VARIANCE_RULES]

    states, ys = jax.vmap(duffing.simulate, (None, 0))(key, jnp.asarray(biases))
    flags = run_bank_scenarios(model, prior, states, ys, biases, BANK.masks)

    def ekf_alarms(ys):
        alarms = []
        for ekf, ekf_init in ekfs:
            post = run_estimator(EKF(), ekf, ys, prior=ekf_init)
            alarms.append(fdi.chi_square_alarms(post.innovation, post.innovation_cov, threshold))
        return jnp.stack(alarms)

    return (*flags, jax.vmap(ekf_alarms)(ys))


def batched_over_runs(one_run):
    """jit of ``keys -> stacked one_run(key)``: one ``vmap`` over every run.

    Earlier versions ran 25 runs at a time inside a ``lax.map``: one vmap over all 200 runs hung
    in about half the executions on a 2-core CPU. The cause was jaxlib 0.10's batched LAPACK
    calls (the EKF's and the filters' small factorisations), two of which running at once can
    deadlock XLA's CPU thread pool (:mod:`jaxest.montecarlo`). The filters now factor their 2x2
    and small matrices in fused ``jnp`` code, and ``tests/test_smf_fdi_batch.py`` checks that the
    compiled study contains no LAPACK call and runs 20 times in a row under a time limit.

    Compiled without YNNPACK fusions (:data:`jaxest.xla_flags.NO_YNN_FUSION`): with all runs,
    scenarios and filters in one batch, XLA:CPU handed its larger fusions to YNNPACK, and the
    study and the containment stress ran 12 % slower (docs/performance.md)."""
    return jax.jit(
        jax.vmap(one_run), compiler_options=xla_flags.compile_options(xla_flags.NO_YNN_FUSION)
    )


def shard_runs(keys):
    """``keys`` placed one block of runs per device, where the process has several devices
    (:func:`jaxest.montecarlo.default_mesh`; on a CPU, :func:`jaxest.xla_flags.cpu_devices`) and
    the runs divide evenly among them; as given otherwise. A program of
    :func:`batched_over_runs` then runs each block on its own device. The Monte Carlo's flags
    are the same bit for bit as on one device (``tests/test_smf_fdi_batch.py``); floating-point
    values XLA computes for the smaller batch may differ in the last bit (the quick study's
    automatic-bound check: largest relative difference 2.42e-15 against 2.45e-15)."""
    mesh = default_mesh()
    if mesh is None or len(keys) % mesh.devices.size:
        return keys
    return jax.device_put(keys, NamedSharding(mesh, PartitionSpec(RUNS_AXIS)))


def monte_carlo_function(closed_form_bound: bool = False):
    """A jitted ``keys -> (inconsistent, contains, unbounded, ekf_alarms)``, each shaped
    (runs, scenarios, filters or rules, steps): the whole Monte Carlo under one vmap.

    Made once per process and argument, as are the study's other programs
    (:func:`containment_stress_function`, :func:`automatic_bound_function`): a later call, or a
    check of the compiled program (``.lower(keys).compile()``), reuses what the study compiled,
    whether the argument is given by position or by name."""
    return _monte_carlo_function(bool(closed_form_bound))


@functools.cache
def _monte_carlo_function(closed_form_bound: bool):
    biases = scenario_biases()
    return batched_over_runs(lambda key: _one_run(key, biases, closed_form_bound))


def single_filter_function(closed_form_bound: bool = False):
    """A jitted ``keys -> inconsistent flags`` of the detection SMF alone over fault-free runs
    (the benchmark's unit of work)."""
    model, prior = duffing.model(closed_form_bound), first_prior(closed_form_bound)

    def one(key):
        _, ys = simulate_run(key, None)
        return run_estimator(SetMembershipFilter(), model, ys, prior=prior).inconsistent

    return batched_over_runs(one)


#: containment stress (fault-free, every filter of the bank): noise scale -> runs (full, quick)
STRESS_RUNS = {1.0: (10_000, 200), 5.0: (1_000, 50)}


def containment_stress_function(noise_scale: float):
    """A jitted ``keys -> (outside, unflagged_not_pd, unbounded)``, each (runs, filters, T), over
    fault-free runs with the noise and its bounds times ``noise_scale`` (closed-form remainder):
    whether the truth left a reported set, whether a set neither positive definite nor flagged
    unbounded was reported, and the UNBOUNDED flags. Made once per process and scale (1 and
    1.0 alike)."""
    return _containment_stress_function(float(noise_scale))


@functools.cache
def _containment_stress_function(noise_scale: float):
    model = duffing.model(closed_form_bound=True, noise_scale=noise_scale)
    prior = SetMembershipFilter().predict(model, duffing.prior())

    def one(key):
        bias = jnp.zeros_like(duffing.sensor_bias(0))
        states, ys = duffing.simulate(key, bias, noise_scale=noise_scale)
        bank = run_bank(model, prior, ys, BANK.masks)
        pd = jax.vmap(jax.vmap(is_positive_definite))(bank.shape)
        return ~bank_contains(bank, states), ~pd & ~bank.unbounded, bank.unbounded

    return batched_over_runs(one)


def containment_stress(seed: int, quick: bool) -> dict:
    """Run :func:`containment_stress_function` at each scale of :data:`STRESS_RUNS`."""
    out = {}
    for scale, (full, small) in STRESS_RUNS.items():
        started = time.perf_counter()
        runs = small if quick else full
        outside, not_pd, unbounded = (
            np.asarray(a)
            for a in containment_stress_function(scale)(
                shard_runs(jax.random.split(jax.random.key(seed), runs))
            )
        )
        out[f"noise_x{scale:g}"] = {
            "runs": runs,
            "containment_rate": float(1.0 - outside.mean()),
            "steps_outside": int(outside.sum()),
            "unflagged_not_positive_definite": int(not_pd.sum()),
            "unbounded_rate_by_filter": {
                name: float(unbounded[:, i].mean()) for i, name in enumerate(BANK.names)
            },
            "wall_seconds": time.perf_counter() - started,
        }
    return out


def summarise(inconsistent, contains, unbounded, ekf_alarms) -> dict:
    """Rates of one Monte Carlo (arrays from :func:`monte_carlo_function`)."""
    inconsistent, contains = np.asarray(inconsistent), np.asarray(contains)
    start = duffing.FAULT_START
    out = {"detection": {}, "isolation_method1": {}, "isolation_method2": {}}
    for s, L in enumerate(LEVELS, start=1):
        for key, scores in fdi_scores(inconsistent[:, s], BANK, 0, start).items():
            out[key][str(L)] = scores
    ekf = np.asarray(ekf_alarms)
    rules = list(VARIANCE_RULES)
    steps = np.arange(ekf.shape[-1]) + 1
    before_fault = np.any(ekf[:, 1:, :, steps < start], axis=-1)  # (runs, L, rules)
    out["ekf_chi2"] = {
        "false_alarm_rate": float(np.mean(before_fault[:, 0, 0])),
        "variance_rule": rules[0],
        "significance": SIGNIFICANCE,
        "false_alarm_rate_by_rule": {
            r: float(np.mean(before_fault[:, 0, i])) for i, r in enumerate(rules)
        },
        "fault_free_alarm_rate_by_rule": {
            r: float(np.mean(np.any(ekf[:, 0, i], axis=-1))) for i, r in enumerate(rules)
        },
    }
    out["containment_rate"] = float(np.mean(contains[:, 0]))
    out["containment_rate_by_filter"] = {
        name: float(np.mean(contains[:, 0, i])) for i, name in enumerate(BANK.names)
    }
    out["fault_free_inconsistency_rate"] = float(np.mean(np.any(inconsistent[:, 0], axis=-1)))
    unb = np.asarray(unbounded)[:, 0]  # (runs, F, T)
    out["unbounded_rate_by_filter"] = {
        name: float(np.mean(np.any(unb[:, i], axis=-1))) for i, name in enumerate(BANK.names)
    }
    sensor2_only = unb[:, BANK.names.index("sensor 2")]
    first = np.where(np.any(sensor2_only, axis=-1), np.argmax(sensor2_only, axis=-1) + 1, -1)
    out["sensor2_only_unbounded_from_step"] = {
        "min": int(first[first > 0].min()) if np.any(first > 0) else None,
        "max": int(first[first > 0].max()) if np.any(first > 0) else None,
    }
    return out


def _seed_spread(summaries: list[dict], seeds: list[int]) -> dict:
    spread = {"seeds": seeds}
    for key in ("detection", "isolation_method1", "isolation_method2"):
        spread[key] = {}
        for L in map(str, LEVELS):
            rates = [s[key][L]["missed_rate"] for s in summaries]
            spread[key][L] = {
                "missed_rate": rates,
                "min": min(rates),
                "max": max(rates),
                "mean": float(np.mean(rates)),
            }
    spread["containment_rate"] = [s["containment_rate"] for s in summaries]
    spread["smf_false_alarm_rate_max"] = max(
        s[k][L]["false_alarm_rate"]
        for s in summaries
        for k in ("detection", "isolation_method1", "isolation_method2")
        for L in map(str, LEVELS)
    )
    return spread


@functools.cache
def automatic_bound_function():
    """A jitted ``keys -> (flags, relative_difference, example)``: the detection SMF with the
    automatic interval remainder bound over every scenario (flags (runs, S, T), to compare with
    the closed-form Monte Carlo), the largest relative difference of the two bounds along those
    runs, and the fault-free run of ``keys[0]`` with the EKF beside it (figs 1-3)."""
    smf, auto, closed = SetMembershipFilter(), duffing.model(False), duffing.model(True)
    prior, biases, ekf = (
        first_prior(False),
        scenario_biases(),
        ekf_model(next(iter(VARIANCE_RULES))),
    )

    def scenario(key, bias):
        states, ys = duffing.simulate(key, bias)
        result = run_estimator(smf, auto, ys, prior=prior)
        closed_bound = jax.vmap(closed.f_remainder)(result.center, result.shape)[:, 1]
        relative = jnp.max(jnp.abs(result.remainder[:, 1] - closed_bound) / closed_bound)
        return result.inconsistent, relative

    def check(keys):
        per_run = lambda k: jax.vmap(lambda b: scenario(k, b))(biases)
        flags, relative = jax.vmap(per_run)(keys)
        states, ys = duffing.simulate(keys[0], biases[0])
        example = (
            states,
            run_estimator(smf, auto, ys, prior=prior),
            run_estimator(EKF(), ekf, ys, prior=ekf_prior(ekf)),
        )
        return flags, jnp.max(relative), example

    return jax.jit(check)


def run(
    out: Path,
    *,
    runs: int | None = None,
    seed: int = 0,
    quick: bool = False,
    options: dict | None = None,
) -> dict:
    started = time.perf_counter()
    runs = runs or (20 if quick else DEFAULT_RUNS)
    seeds = [seed, seed + 1] if quick else list(range(seed, seed + SEEDS))
    directory = Path(out) / NAME
    directory.mkdir(parents=True, exist_ok=True)
    study = monte_carlo_function(closed_form_bound=True)
    summaries = []
    with Progress(NAME, total=len(seeds) + 2) as progress:
        for s in seeds:
            keys = jax.random.split(jax.random.key(s), runs)
            outputs = study(shard_runs(keys))
            if s == seed:
                first_flags = np.asarray(outputs[0][:, :, 0])
            summaries.append(summarise(*outputs))
            progress.advance(f"seed {s}")
        flags, relative, example = automatic_bound_function()(
            shard_runs(jax.random.split(jax.random.key(seed), runs))
        )
        _figures(directory, *example)
        progress.advance("automatic bound check, figures")
        stress = containment_stress(seed, quick)
        progress.advance("containment stress")
    summary = dict(summaries[0])
    summary.update(
        runs=runs,
        seed=seed,
        seed_spread=_seed_spread(summaries, seeds),
        remainder_bound="closed form (eq 42) in the Monte Carlo; the automatic interval bound is checked beside it",
        automatic_bound_check={
            "max_relative_difference": float(relative),
            "same_detection_flags": bool(np.array_equal(np.asarray(flags), first_flags)),
        },
        containment_stress=stress,
        paper=PAPER,
        wall_seconds=time.perf_counter() - started,
    )
    _tables(directory, summary)
    write_json(directory / "summary.json", summary)
    return summary


def _tables(directory: Path, summary: dict) -> None:
    headers = ["L", "missed %", "paper missed %", "missed % over seeds (min-max)", "false alarm %",
               "min delay", "max delay", "mean delay", "paper min/max/mean delay"]  # fmt: skip
    text = "# smf-fdi\n\n"
    for title, key, paper_key in (
        ("Table 2: fault detection", "detection", "detection"),
        (
            "Table 3: fault isolation, method 1 (one sensor per filter)",
            "isolation_method1",
            "isolation",
        ),
        (
            "Table 3: fault isolation, method 2 (all sensors but one)",
            "isolation_method2",
            "isolation",
        ),
    ):
        rows = []
        for L in map(str, LEVELS):
            ours, paper, spread = (
                summary[key][L],
                PAPER[paper_key][L],
                summary["seed_spread"][key][L],
            )
            rows.append([
                L, 100 * ours["missed_rate"], 100 * paper["missed_rate"],
                f"{100 * spread['min']:.1f}-{100 * spread['max']:.1f}", 100 * ours["false_alarm_rate"],
                ours["min_delay"], ours["max_delay"], ours["mean_delay"],
                f"{paper['min_delay']}/{paper['max_delay']}/{paper['mean_delay']}",
            ])  # fmt: skip
        text += f"## {title}\n\n" + markdown_table(headers, rows, floatfmt=".3g") + "\n"
    ekf = summary["ekf_chi2"]
    rows = [[rule, 100 * rate] for rule, rate in ekf["false_alarm_rate_by_rule"].items()]
    text += f"## EKF + chi-square test (significance {ekf['significance']} per step)\n\n"
    text += markdown_table(
        ["Q, R from the boxes", "false alarm % (alarm before k = 50)"], rows, floatfmt=".3g"
    )
    text += f"\nSMF containment rate (fault-free runs, every step and filter): {summary['containment_rate']}\n"
    (directory / "tables.md").write_text(text)


def _figures(directory: Path, states, result, post) -> None:
    from jaxest.plot import plt, save

    k = np.arange(1, states.shape[0] + 1)
    for name, centre, half in (
        (
            "fig1_smf_bounds.png",
            result.center,
            jnp.sqrt(jnp.diagonal(result.shape, axis1=1, axis2=2)),
        ),
        ("fig2_ekf_bounds.png", post.mean, 3 * jnp.sqrt(jnp.diagonal(post.cov, axis1=1, axis2=2))),
    ):
        fig, axes = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
        for i, ax in enumerate(axes):
            ax.plot(k, states[:, i], "k-", lw=1, label="true state")
            ax.plot(k, centre[:, i] + half[:, i], "b--", lw=1, label="upper bound")
            ax.plot(k, centre[:, i] - half[:, i], "r--", lw=1, label="lower bound")
            ax.set_ylabel(f"x{i + 1}")
        axes[0].legend()
        axes[0].set_title("SMF state bounds" if "smf" in name else "EKF 3-sigma bounds")
        axes[-1].set_xlabel("k")
        save(fig, directory / name, dpi=100)
    fig, ax = plt.subplots(figsize=(7, 3.5))
    ax.plot(k, result.remainder[:, 1], "b-")
    ax.set_xlabel("k")
    ax.set_ylabel("alpha_2 (remainder bound)")
    ax.set_title("Upper bound of the linearisation remainder of f_2")
    save(fig, directory / "fig3_remainder_bound.png", dpi=100)
