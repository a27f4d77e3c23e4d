"""Set-membership estimation: interval arithmetic, ellipsoid operations, the nonlinear ellipsoidal
set-membership filter and guaranteed sensor fault detection and isolation (Chai & Sun 2007)."""

from jaxest.setmembership.ellipsoid import (
    Ellipsoid,
    add_box,
    add_segment,
    contains,
    intersect_strip,
    strips_ellipsoid,
)
from jaxest.setmembership.interval import Interval, hessian_interval, remainder_bound
from jaxest.setmembership.smf import (
    BoundedNoiseModel,
    SetMembershipFilter,
    SMFResult,
    set_membership_filter,
)
from jaxest.setmembership.status import SetStatus

__all__ = [
    "BoundedNoiseModel",
    "Ellipsoid",
    "Interval",
    "SMFResult",
    "SetStatus",
    "SetMembershipFilter",
    "add_box",
    "add_segment",
    "contains",
    "hessian_interval",
    "intersect_strip",
    "remainder_bound",
    "set_membership_filter",
    "strips_ellipsoid",
]
