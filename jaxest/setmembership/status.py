"""The set-membership family's status flags: the core's and its own."""

from jaxest._status import Status

SetStatus = Status.extend(
    "SetStatus",
    EMPTY_SET=(
        4,
        "the measurements are inconsistent with the predicted set: a sensor fault, or noise "
        "bounds that are too tight",
    ),
    UNBOUNDED=(
        8,
        "the set grew without bound (it contains everything): the state is not observable from "
        "the measurements used",
    ),
    ILL_CONDITIONED=(
        32,
        "the filtered or predicted shape matrix lost definiteness or passed the condition number "
        "float arithmetic can carry (max_condition); the set is declared unbounded",
    ),
    RECOVERED=(
        256,
        "the filter had lost its set (UNBOUNDED) and re-initialised at this step from the "
        "measurement strips alone: h is affine and the observed rows constrain every direction "
        "(not an error; the set is guaranteed again from here on)",
    ),
)
"""The set-membership filters' status flags: the core's and their own."""
