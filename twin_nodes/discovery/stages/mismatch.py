"""Stage 2, the located mismatch: the nominal's residuals, and where they are above each channel's
noise floor, labelled by regime (``PreparedFlight`` -> ``Mismatch``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twin_nodes.discovery.locate import locate, locate_output
from twin_nodes.discovery.residuals import residual_channels
from twin_nodes.discovery.stages.prepare import PreparedFlight


@dataclass
class Mismatch:
    """The nominal model against the flight."""

    R_base: np.ndarray            # its equation error (low-passed), every grid sample
    base_held: np.ndarray         # its held-out RMS per equation-error channel
    windows: list[dict]           # mismatch windows (equation and output error), most severe first
    oe_base: np.ndarray | None    # its output error per window (None: no output error)


def run(flight: PreparedFlight) -> Mismatch:
    """Locate the mismatch of the nominal (``flight.nominal``) on every channel."""
    data, names, vp, oe = flight.data, flight.names, flight.nominal, flight.oe
    R_base = residual_channels(data, vp, vp)
    raw_base = residual_channels(data, vp, vp, lowpass_hz=None)
    base_held = np.sqrt(np.mean(R_base[flight.held_mask] ** 2, axis=0))
    mismatch = locate(data, R_base, raw_base, names, vp)
    oe_base = oe.residual(vp) if oe else None
    if oe is not None:
        mismatch = sorted(mismatch + locate_output(data, oe.windows, oe_base, vp), key=lambda d: -d["severity"])
    return Mismatch(R_base, base_held, mismatch, oe_base)
