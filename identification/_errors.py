"""Error type of the identification layer."""

from __future__ import annotations


class IdentificationError(ValueError):
    """Bad input to, or an impossible request of, the identification layer.

    The message names the argument (``freq_hz``, ``H``, ``order``, ``band_hz``,
    ``weights``...) and what is wrong with it.
    """
