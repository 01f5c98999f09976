"""identification layer (see ARCHITECTURE.md).

Frequency-domain subspace identification from FRFs (McKelvey, Akcay & Ljung
1996) in continuous time, pole labelling and stabilization, modal parameters,
damping equalization (paper Eq. 2.7-2.13) and fit quality. Arrays in, frozen
results out; imports only numpy and scipy (matplotlib lazily, for plots).
"""

from ._equalize import equalized
from ._errors import IdentificationError
from ._identify import Identification, default_block_rows, identify
from ._order import DEFAULT_MAX_ORDER, OrderSelection, select_order
from ._metrics import channel_deviation, log_ratio, square_deviation
from ._plots import plot_fit, plot_stabilization
from ._poles import LABELS, ModalParameters, Poles, mac
from ._stabilization import Stabilization, stabilization
from ._statespace import StateSpace
from ._subspace import bilinear_alpha, to_continuous, to_discrete

__all__ = [
    "DEFAULT_MAX_ORDER",
    "OrderSelection",
    "select_order",
    "LABELS",
    "Identification",
    "IdentificationError",
    "ModalParameters",
    "Poles",
    "Stabilization",
    "StateSpace",
    "bilinear_alpha",
    "channel_deviation",
    "default_block_rows",
    "equalized",
    "identify",
    "log_ratio",
    "mac",
    "plot_fit",
    "plot_stabilization",
    "square_deviation",
    "stabilization",
    "to_continuous",
    "to_discrete",
]
