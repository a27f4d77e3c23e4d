"""Argument checks that run before anything is traced.

Shapes are always checked; values (symmetry, definiteness, NaN) are checked when the arrays are
concrete, i.e. not JAX tracers (inside a user's ``jit`` the values are unknown until run time, and
trouble then shows in the result's ``status`` instead). Models are read through their methods
(:class:`~jaxest.models.AbstractGaussianModel`), so a user's own model gets the same errors as the
built-in ones.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxest._priors import Gaussian
from jaxest.models import (
    AbstractGaussianModel,
    LinearGaussian,
    NonlinearGaussian,
    check_inputs_used,
    check_time_axes,
)
from jaxest.scaling import ScaledState


def is_concrete(x) -> bool:
    """True for arrays whose values are known now (not tracers inside jit/vmap/grad)."""
    return not isinstance(x, jax.core.Tracer)


def concrete_k0(k0, meaning: str) -> int | None:
    """``k0`` as an int where its value is known now (``None`` for a tracer), after checking it
    is a non-negative integer (``ValueError`` naming ``k0`` and what it indexes, ``meaning``)."""
    if not is_concrete(k0):
        return None
    index = np.asarray(k0)
    if index.dtype.kind not in "iu" or index.ndim != 0 or index < 0:
        raise ValueError(
            f"k0: expected a non-negative integer (the index of {meaning}), got {k0!r}"
        )
    return int(index)


def check_positive_int(name: str, value) -> None:
    """``value`` is an integer of at least 1, Python's or NumPy's (a count: runs, iterations;
    not a bool)."""
    if not _is_integer(value) or value < 1:
        raise ValueError(f"{name}: must be a positive integer, got {value!r}")


def check_callable(name: str, value) -> None:
    """``value`` can be called (the user's function: a loss, one Monte Carlo run)."""
    if not callable(value):
        raise ValueError(f"{name}: expected a function, got {type(value).__name__}")


def check_flag(name: str, value, *, none: bool = False) -> None:
    """``value`` is True or False (or ``None`` where ``none``): a switch, where a string such
    as ``"no"`` would otherwise count as true."""
    if not (isinstance(value, bool | np.bool_) or none and value is None):
        allowed = "True, False or None" if none else "True or False"
        raise ValueError(f"{name}: expected {allowed}, got {value!r}")


def check_nonnegative_int(name: str, value) -> None:
    """``value`` is an integer of at least 0, Python's or NumPy's, not a bool (a count that may
    be zero: steps)."""
    if not _is_integer(value) or value < 0:
        raise ValueError(f"{name}: must be a non-negative integer, got {value!r}")


def _is_integer(value) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool | np.bool_)


def check_key(name: str, key) -> None:
    """``key`` is one PRNG key: a typed key (``jax.random.key``, any implementation) of shape
    (), or the raw uint32 vector of ``jax.random.PRNGKey``; JAX's own errors for an int seed, a
    batch of keys or an int32 vector name no argument."""
    dtype = getattr(key, "dtype", None)
    if dtype is not None and jnp.issubdtype(dtype, jax.dtypes.prng_key):
        if np.shape(key) != ():
            raise ValueError(f"{name}: expected one PRNG key, got a batch of shape {np.shape(key)}")
    elif dtype != np.uint32 or np.ndim(key) != 1:
        got = f"{dtype} array of shape {np.shape(key)}" if dtype is not None else repr(key)
        raise ValueError(f"{name}: expected a PRNG key (jax.random.key(seed)), got {got}")


def as_array(name: str, value):
    """``value`` itself if it is an array (JAX or NumPy), a Python number as a NumPy array.
    Anything else, a list included, is a ``ValueError`` naming ``name``: JAX's functions take
    no lists (a list inside a model is a pytree of scalars, one argument each under ``jit``),
    and failed deep inside the library with a ``TypeError`` that named no argument."""
    if hasattr(value, "shape") and hasattr(value, "ndim") and hasattr(value, "dtype"):
        return value
    if isinstance(value, int | float) and not isinstance(value, bool):
        return np.asarray(value, dtype=float)
    hint = "; convert it with jnp.asarray" if isinstance(value, list | tuple) else ""
    raise ValueError(f"{name}: expected an array, got {type(value).__name__}{hint}")


def check_operands(shape, vectors: dict, scalars: dict | None = None) -> None:
    """``ValueError`` naming the argument unless ``shape`` (an ellipsoid's shape matrix) is an
    (n, n) matrix, each of ``vectors`` (name: value) has shape (n,) and each of ``scalars``
    shape (), all real floating point (a Python number is taken as a float): the operands of
    the set-membership building blocks. A wrong length failed inside JAX with a broadcasting
    error that named no argument, and an integer array in the rounding bounds (an integer type
    has no unit roundoff). Shapes and dtypes are known when tracing: this holds under ``jit``
    and ``vmap``."""
    operands = {"shape": shape} | vectors | (scalars or {})
    arrays = {name: as_array(name, value) for name, value in operands.items()}
    got = arrays["shape"].shape
    if len(got) != 2 or got[0] != got[1]:
        raise ValueError(f"shape: expected a square (n, n) matrix, got shape {got}")
    n = got[0]
    for name, array in arrays.items():
        expected = (n, n) if name == "shape" else (n,) if name in vectors else ()
        if array.shape != expected:
            raise ValueError(f"{name}: expected shape {expected} (n = {n}), got {array.shape}")
        if not jnp.issubdtype(array.dtype, jnp.floating):
            raise ValueError(f"{name}: must be real floating point, got {array.dtype}")


def check_matrix(name: str, value, shape=None, *, square=False, spd=False, psd=False, ndim=2):
    """Raise ``ValueError`` naming ``name`` unless ``value`` is a well-formed matrix.

    ``ndim`` is the matrix's own rank; one extra leading axis (time) is allowed.
    ``shape`` (trailing dims, ``None`` entries are free) is checked against the last ``ndim`` axes.
    ``spd``/``psd`` require a symmetric positive (semi)definite matrix (checked when concrete).
    """
    arr = as_array(name, value)
    if arr.ndim not in (ndim, ndim + 1):
        raise ValueError(
            f"{name}: expected {ndim} dims (or {ndim + 1} with a time axis), got shape {arr.shape}"
        )
    trailing = arr.shape[arr.ndim - ndim :]
    if shape is not None:
        for want, got in zip(shape, trailing, strict=True):
            if want is not None and want != got:
                raise ValueError(f"{name}: expected trailing shape {tuple(shape)}, got {arr.shape}")
    if (square or spd or psd) and trailing[-1] != trailing[-2]:
        raise ValueError(f"{name}: must be square, got shape {arr.shape}")
    if jnp.issubdtype(arr.dtype, jnp.complexfloating):
        raise ValueError(f"{name}: must be real, got dtype {arr.dtype}")
    if not is_concrete(arr):
        return
    a = np.asarray(arr, dtype=np.float64)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: contains NaN or infinite entries")
    if spd or psd:
        precision = arr.dtype if jnp.issubdtype(arr.dtype, jnp.floating) else np.float64
        check_symmetric_definite(name, a, strict=spd, eps=float(jnp.finfo(precision).eps))


def check_symmetric_definite(name: str, a: np.ndarray, *, strict: bool, eps: float):
    """Symmetric and positive definite (``strict``) or semidefinite, for a concrete array held in
    a precision of machine epsilon ``eps``: semidefinite allows eigenvalues down to -max(1e-12,
    10 n eps) times the largest entry, a float32 product G Q G^T (or g g^T) of rank below n
    rounds to eigenvalues of -1e-9 relative, which a float64 tolerance refused.

    Positive definite means definite beyond rounding: the matrix scaled to a unit diagonal (its
    correlation matrix, so that states in different units are not taken for a near-singular
    one) has its smallest eigenvalue above 10 n eps. A rank-one g g^T rounds to a smallest
    eigenvalue of +1e-20, which passed, and the filters that factor it returned NaN."""
    scale = max(np.max(np.abs(a)), np.finfo(np.float64).tiny)
    if np.max(np.abs(a - np.swapaxes(a, -1, -2))) > 1e-6 * scale:
        raise ValueError(f"{name}: must be symmetric")
    a = 0.5 * (a + np.swapaxes(a, -1, -2))
    smallest = np.min(np.linalg.eigvalsh(a))
    if strict and smallest <= 0:
        raise ValueError(f"{name}: must be positive definite (smallest eigenvalue {smallest:.3g})")
    if strict:
        root = np.sqrt(np.diagonal(a, axis1=-2, axis2=-1))  # positive: a's eigenvalues are
        correlation = np.min(np.linalg.eigvalsh(a / (root[..., :, None] * root[..., None, :])))
        if correlation <= 10 * a.shape[-1] * eps:
            raise ValueError(
                f"{name}: must be positive definite beyond rounding: singular to {eps:.2g} "
                f"precision (smallest eigenvalue {smallest:.3g}, {correlation:.3g} scaled to a "
                f"unit diagonal)"
            )
    if not strict and smallest < -max(1e-12, 10 * a.shape[-1] * eps) * scale:
        raise ValueError(
            f"{name}: must be positive semidefinite (smallest eigenvalue {smallest:.3g})"
        )


#: what a user who passed one input for the whole run (no time axis) needs to hear
_ONE_INPUT_PER_STEP = (
    "; inputs hold u_k for every step on a leading time axis (a constant u for T steps is "
    "jnp.broadcast_to(u, (T,) + u.shape))"
)


def check_sequence(name: str, value, length=None, dim=None, dim_source: str = ""):
    """``value`` must be (T, dim); ``length`` is the T it must match (``None``: any)."""
    if value is None:
        raise ValueError(f"{name}: expected an array with a leading time axis, got None")
    shape = as_array(name, value).shape
    if len(shape) != 2:
        raise ValueError(f"{name}: expected shape (T, {dim if dim else 'd'}), got {shape}")
    if length is not None and shape[0] != length:
        raise ValueError(
            f"{name}: has {shape[0]} time steps but the measurements have {length}"
            + (_ONE_INPUT_PER_STEP if name == "inputs" else "")
        )
    if dim is not None and shape[1] != dim:
        raise ValueError(f"{name}: expected {dim} column(s){dim_source}, got {shape[1]}")


def check_inputs(inputs, length: int, steps: str) -> None:
    """``inputs``: an array, or a pytree of arrays, each with a leading time axis of ``length``
    steps (u_k is the k-th slice of every leaf) and, where concrete, finite (an input is never
    missing: a NaN one made every later estimate NaN, flagged only as ``NONFINITE``); ``steps``
    says where ``length`` comes from ("the measurements have 10")."""
    leaves = jax.tree_util.tree_leaves_with_path(inputs)
    if not leaves:
        raise ValueError("inputs: holds no arrays; pass None for a model without inputs")
    for path, leaf in leaves:
        name = "inputs" + jax.tree_util.keystr(path)
        shape = np.shape(as_array(name, leaf))
        if not shape:
            raise ValueError(
                f"{name}: expected a leading time axis of {length} steps, got a scalar"
            )
        if shape[0] != length:
            raise ValueError(f"{name}: has {shape[0]} time steps but {steps}{_ONE_INPUT_PER_STEP}")
        if is_concrete(leaf) and not np.all(np.isfinite(np.asarray(leaf))):
            raise ValueError(
                f"{name}: has NaN or infinite entries (an input is never missing; NaN marks a "
                "missing measurement in ys only)"
            )


def check_measurements(ys):
    """``ys`` is a (T, m) array, real, and has no +-inf (NaN marks a missing entry; inf is an
    error)."""
    check_sequence("ys", ys)
    if jnp.issubdtype(jnp.result_type(ys), jnp.complexfloating):
        raise ValueError(f"ys: must be real, got {jnp.result_type(ys)}")
    if is_concrete(ys) and np.any(np.isinf(np.asarray(ys, dtype=np.float64))):
        raise ValueError("ys: contains +-inf entries (only NaN marks a missing measurement)")


def check_complete(ys, needs: str) -> None:
    """``ys`` has no missing (NaN) entries, for estimators that cannot skip them (``needs``
    says which and why), when concrete."""
    if is_concrete(ys) and np.any(np.isnan(np.asarray(ys, dtype=np.float64))):
        raise ValueError(f"ys: has missing (NaN) entries; {needs}")


def check_gaussian_prior(prior, n: int | None = None) -> int:
    """``prior`` is a :class:`~jaxest.Gaussian` with a vector mean and an SPD covariance."""
    if not isinstance(prior, Gaussian):
        raise ValueError(f"prior: expected jaxest.Gaussian(mean, cov), got {type(prior).__name__}")
    return check_prior_arrays(prior, "mean", "cov", n)


def check_prior_vector(prior, field: str, n: int | None = None) -> int:
    """The prior's field ``field`` (a Gaussian's mean, an ellipsoid's center, an observer's x or
    theta): real floating point (an integer one changed the scan's carry, or failed in
    ``jacfwd``), a vector of size ``n`` (the model's, where given), finite (its values checked
    where concrete). Returns its size."""
    name, value = f"prior.{field}", getattr(prior, field)
    dtype = as_array(name, value).dtype
    if not jnp.issubdtype(dtype, jnp.floating):
        raise ValueError(f"{name}: must be real floating point, got {dtype}")
    if np.ndim(value) != 1:
        raise ValueError(f"{name}: expected a vector, got shape {np.shape(value)}")
    size = np.shape(value)[0]
    if n is not None and size != n:
        raise ValueError(f"{name}: expected shape ({n},) to match the model, got ({size},)")
    check_matrix(name, value, (size,), ndim=1)  # finite
    return size


def check_prior_arrays(prior, vector: str, matrix: str, n: int | None = None) -> int:
    """The prior's fields ``vector`` (a Gaussian's mean, an ellipsoid's center;
    :func:`check_prior_vector`) and ``matrix`` (its cov, shape): real floating point and a
    symmetric positive definite matrix of the vector's size (values checked where concrete).
    Returns the size."""
    size = check_prior_vector(prior, vector, n)
    spread = getattr(prior, matrix)
    dtype = as_array(f"prior.{matrix}", spread).dtype
    if not jnp.issubdtype(dtype, jnp.floating):
        raise ValueError(f"prior.{matrix}: must be real floating point, got {dtype}")
    if np.ndim(spread) != 2:
        raise ValueError(f"prior.{matrix}: expected shape ({size}, {size}), got {np.shape(spread)}")
    check_matrix(f"prior.{matrix}", spread, (size, size), spd=True)
    return size


def first_input(inputs):
    """u_0 of a leading-time-axis array, or zeros of its shape when there are no steps (T = 0),
    for the checks' evaluation of the model."""
    return inputs[0] if inputs.shape[0] else jnp.zeros(inputs.shape[1:], inputs.dtype)


def check_gaussian_arguments(model, ys, inputs, prior, *, positive_Q: bool | str = False):
    """All checks of a Gaussian filter's arguments (:func:`jaxest.run`).

    ``positive_Q``: the filter inverts or factors Q, so Q must be positive definite (a string:
    what else to do, where other filters are not the way out).
    """
    if not isinstance(model, AbstractGaussianModel):
        raise ValueError(
            f"model: expected a Gaussian model (a subclass of jaxest.AbstractGaussianModel, "
            f"e.g. LinearGaussian or NonlinearGaussian), got {type(model).__name__}"
        )
    if isinstance(model, ScaledState):  # check the model it scales, on the prior in its units
        n = check_gaussian_prior(prior)
        if np.shape(model.scale) != (n,):
            raise ValueError(
                f"model.scale: has shape {np.shape(model.scale)}, expected ({n},) as the prior"
            )
        check_precision(model, ys, prior)  # a float64 scale on a float32 prior widens the state
        unscaled = Gaussian(model.state_mean(prior.mean), model.state_cov(prior.cov))
        check_gaussian_arguments(model.model, ys, inputs, unscaled, positive_Q=positive_Q)
        return
    T = _check_data(ys, inputs)
    check_inputs_used(model, inputs)
    n = linear_state_dim(model, prior) if isinstance(model, LinearGaussian) else None
    n = check_gaussian_prior(prior, n)
    check_precision(model, ys, prior)
    shapes, u0 = _check_width(model, ys, inputs, prior.mean, "prior.mean")
    m = shapes["h(x)"][0]
    q = check_model_shapes(model, shapes, n, "prior.mean")
    check_noise_values(model, prior.mean, u0, T, m, q, positive_Q)


def _check_data(ys, inputs) -> int:
    """``ys`` a (T, m) real array without inf, ``inputs`` (where given) of T steps; returns T."""
    check_measurements(ys)
    T = np.shape(ys)[0]
    if inputs is not None:
        check_inputs(inputs, T, f"the measurements have {T}")
    return T


def _check_width(model, ys, inputs, x, state: str) -> tuple[dict, object]:
    """``ys`` as wide as the model's h(x) at ``x`` (named ``state`` where the model cannot be
    evaluated there; ys is blamed for the width); returns the model's shapes there
    (:func:`model_shapes`) and u_0."""
    u0 = None if inputs is None else jax.tree.map(first_input, inputs)
    shapes = model_shapes(model, x, u0, state)
    m = shapes["h(x)"][0]
    check_sequence("ys", ys, dim=m, dim_source=f" (the model's h(x) has {m} entries)")
    return shapes, u0


def check_resumed_arguments(model, ys, inputs, mean) -> None:
    """The checks of :func:`check_gaussian_arguments` that need no prior, for a run resumed from
    a state (``run(..., state=...)``): ``ys`` a (T, m) real array without inf, ``inputs`` of T
    steps, and, for a Gaussian model, inputs given where it has input matrices and ``ys`` as wide
    as h(x) at ``mean``, the resumed state's mean (not checked where it has none: ``None`` or
    not a vector). A resumed run skipped every check: a model with B run without its inputs gave
    other means with status OK."""
    _check_data(ys, inputs)
    if isinstance(model, ScaledState):
        model = model.model  # the same h(x) and inputs; shapes do not depend on the units
    if not isinstance(model, AbstractGaussianModel):
        return
    check_inputs_used(model, inputs)
    if mean is not None and np.ndim(mean) == 1:
        _check_width(model, ys, inputs, mean, "state.mean")


def check_model_shapes(model, shapes: dict[str, tuple], n: int, state: str) -> int | None:
    """What the model returns (``shapes``, :func:`model_shapes`) fits a state of size ``n``
    (the size of ``state``, named in the error) and its own h(x); returns the process noise's
    size q (``None`` where its G is not a matrix)."""
    m = shapes["h(x)"][0]
    q = shapes["G"][-1] if len(shapes["G"]) == 2 else None
    expected = {
        "f(x)": (n,), "F": (n, n), "G": (n, q), "Q": (q, q),
        "h(x)": (m,), "H": (m, n), "R": (m, m),
    }  # fmt: skip
    builtin = isinstance(model, LinearGaussian | NonlinearGaussian)
    for name, want in expected.items():
        if shapes[name] != want:
            where = f"model.{name}" if builtin and name in "FGHQR" else f"model: its {name}"
            raise ValueError(
                f"{where}: has shape {shapes[name]}, expected {want} for a state of "
                f"size {n} ({state}) and {m} measurements"
            )
    return q


def check_precision(model, ys, prior, *, name: str = "prior", **updated_with) -> None:
    """The prior (a Gaussian, an ellipsoid, or the state alone, named ``name``) in the widest
    precision of itself, the model's arrays, the measurements and any other array it is updated
    with (``updated_with``, by name): a narrower one (a float32 prior with a float64 model) made
    the estimator's state change dtype after one step, a TypeError from inside the scan."""
    inexact = lambda tree: [a for a in jax.tree.leaves(tree) if eqx.is_inexact_array(a)]
    if not inexact(prior):  # an integer one changed the scan's carry
        dtypes = ", ".join(sorted({str(jnp.result_type(a)) for a in jax.tree.leaves(prior)}))
        raise ValueError(f"{name}: must be real floating point, got {dtypes}")
    own = jnp.result_type(*inexact(prior))
    model_arrays = inexact(model)
    widths = {"model": jnp.result_type(*model_arrays)} if model_arrays else {}
    widths["ys"] = jnp.result_type(ys)
    widths |= {other: jnp.result_type(a) for other, a in updated_with.items()}
    if jnp.result_type(own, *widths.values()) != own:
        given = ", ".join(f"{other} {dtype}" for other, dtype in widths.items())
        raise ValueError(
            f"{name}: is {own}, narrower than what it is updated with ({given}); give all of "
            f"them one precision"
        )


def linear_state_dim(model: LinearGaussian, prior) -> int:
    """n of a linear model, blaming whichever of model.F, model.H and the prior disagrees with
    the other two; every matrix of the model an array (a list Q was blamed on prior.mean, where
    the model could not be evaluated)."""
    check_matrix("model.F", model.F, (None, None), square=True)
    check_matrix("model.H", model.H, (None, None))
    for name in ("G", "Q", "R", "B", "D"):  # arrays, before the model is evaluated with them
        if getattr(model, name) is not None:
            as_array(f"model.{name}", getattr(model, name))
    n_F, n_H = np.shape(model.F)[-1], np.shape(model.H)[-1]
    n_prior = np.shape(getattr(prior, "mean", None))[-1:] or (None,)
    if n_F != n_H:
        odd, n = ("model.F", n_H) if n_H == n_prior[0] else ("model.H", n_F)
        raise ValueError(
            f"{odd}: does not fit a state of size {n} (the prior and the other "
            f"matrix agree on {n}); got F {np.shape(model.F)}, H {np.shape(model.H)}"
        )
    return n_F


#: :func:`model_shapes` by :func:`_abstract_signature` of its arguments, newest last
_SHAPES_SEEN: dict = {}
#: how many signatures :data:`_SHAPES_SEEN` keeps
_SHAPES_KEPT = 64


def _abstract_signature(tree):
    """What the model's output shapes can depend on: the tree's structure (static fields
    included), each array leaf's shape and dtype and every other leaf itself (Python numbers,
    functions). ``None`` where a leaf is neither an array nor hashable."""
    leaves, treedef = jax.tree.flatten(tree)
    signature = [treedef]
    for leaf in leaves:
        if hasattr(leaf, "shape") and hasattr(leaf, "dtype"):
            signature.append((tuple(leaf.shape), leaf.dtype))
        else:
            signature.append((type(leaf), leaf))
    signature = tuple(signature)
    try:
        hash(signature)  # static fields are part of the structure, and may not hash
    except TypeError:
        return None
    return signature


def model_shapes(model, x, u, state: str = "prior.mean") -> dict[str, tuple]:
    """Shapes of what the model's methods return at ``x`` (abstractly: nothing is computed);
    a model that cannot be evaluated there is an error naming ``state``, where ``x`` comes from.

    Remembered for the last :data:`_SHAPES_KEPT` signatures: tracing a model's transition and
    its Jacobian (an RK4 flight model: 0.2 s) is otherwise repeated by every :func:`jaxest.run`
    on it, and again inside each trace of a function that calls it."""
    signature = _abstract_signature((model, x, u))
    if signature is not None and signature in _SHAPES_SEEN:
        return _SHAPES_SEEN[signature]
    shapes = _evaluate_shapes(model, x, u, state)
    if signature is not None:
        _SHAPES_SEEN[signature] = shapes
        if len(_SHAPES_SEEN) > _SHAPES_KEPT:
            del _SHAPES_SEEN[next(iter(_SHAPES_SEEN))]
    return shapes


def _evaluate_shapes(model, x, u, state: str) -> dict[str, tuple]:
    try:
        f, F, G, Q = jax.eval_shape(model.transition, x, u, 0)
        h, H, R = jax.eval_shape(model.observation, x, u, 0)
    except Exception as err:  # noqa: BLE001 - reported with the argument's name
        if u is None and "NoneType" in str(err):  # a function that reads u, given none
            raise ValueError(
                f"inputs: the model cannot be evaluated with u = None and k = 0 (no inputs were "
                f"given; {type(err).__name__}: {err}); if its functions read u, pass "
                f"inputs= with a leading time axis (they are called as (x), (x, u) or (x, u, k))"
            ) from err
        # either may be at fault: a flight model given 5 input channels of 6 blamed the state
        blamed, inputs, sizes = (
            (state, "u = None", "the state's size")
            if u is None
            else (f"{state} or inputs", f"u of shape {jax.tree.map(np.shape, u)}",
                  "the state's size and the inputs' width")
        )  # fmt: skip
        raise ValueError(
            f"{blamed}: the model cannot be evaluated at a state of shape {np.shape(x)} "
            f"with {inputs} and k = 0 ({type(err).__name__}: {err}); check {sizes}, "
            f"and that the model's functions take (x), (x, u) or (x, u, k)"
        ) from err
    names = ("f(x)", "F", "G", "Q", "h(x)", "H", "R")
    named = dict(zip(names, (f, F, G, Q, h, H, R), strict=True))
    for name, value in named.items():
        if not isinstance(value, jax.ShapeDtypeStruct):
            raise ValueError(
                f"model: its {name} is a {type(value).__name__}, not an array; return a jax "
                f"array (jnp.stack, jnp.asarray)"
            )
    for name in ("f(x)", "h(x)"):
        if named[name].ndim == 0:
            raise ValueError(
                f"model: its {name} is a scalar; return a vector, of shape (1,) for one entry "
                f"(x[:1], not x[0])"
            )
    return {name: tuple(a.shape) for name, a in named.items()}


def check_noise_values(model, x, u, T, m, q, positive_Q):
    """Q (R) symmetric positive semidefinite (definite), named as the model holds them."""
    if isinstance(model, LinearGaussian | NonlinearGaussian):
        check_matrix("model.R", model.R, (m, m), spd=True)
        check_process_noise("model.Q", model.Q, q, positive_Q)
        check_time_axes(model, 0, T)
        return
    if not all(is_concrete(a) for a in jax.tree.leaves((model, x, u))):
        return
    _, Q = model.process_noise(x, u, 0)
    check_matrix("model.measurement_cov(k=0)", model.measurement_cov(0), (m, m), spd=True)
    check_process_noise("model.process_noise(k=0) Q", Q, q, positive_Q)


def check_process_noise(name: str, Q, q: int, positive: bool | str) -> None:
    """Q symmetric positive semidefinite, and definite where the filter factors it
    (``positive``; a string says what else to do), saying what to do with a rank-deficient
    one."""
    check_matrix(name, Q, (q, q), psd=True)
    if not positive:
        return
    try:
        check_matrix(name, Q, (q, q), spd=True)
    except ValueError as error:
        otherwise = (
            positive if isinstance(positive, str) else "use KalmanFilter, EKF or an SVD filter"
        )
        raise ValueError(
            f"{error}; this filter factors Q: give a rank-deficient noise as G (n x q) with a "
            f"positive definite q x q Q, or {otherwise}"
        ) from None
