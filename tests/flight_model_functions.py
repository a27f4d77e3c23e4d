"""What the tests of the ATTAS benchmark scripts' extended flight models share: the setting they
build the models in, and one compiled evaluation of a model's h, f and G."""

import equinox as eqx

from jaxest.studies import svd_ekf

#: ATTAS sample interval (s), the simulator's input noise, the real records' output noise
DT, INPUT_STD, OUTPUT_STD = 0.04, svd_ekf.sim.INPUT_STD, svd_ekf.REAL_OUTPUT_STD


@eqx.filter_jit  # one program per model: op by op, RK4 and its Jacobian take seconds
def functions_at(model, x, u):
    """(h(x, u), f(x, u), G(x, u)) of ``model``."""
    return model.observation_fn(x, u), model.transition_fn(x, u), model.noise_gain(x, u)
