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
)
