"""The USM glider's depth and pitch dynamics (paper eq. 12 and 13) behind a verified inner loop.

Why not the paper's compensated models (eq. 14–19): they are printed with rounded
coefficients and are not stable as printed (eq. 16 has poles of modulus 1.0032, eq. 19
poles of modulus 8.7 and 2.1, eq. 18 right-half-plane poles), and no discrete PID under
unity feedback stabilises eq. 12 or 13 (a random search of 20,000 gains found spectral
radii of at best 1.0010 and 1.0106). So the emulator keeps the open-loop plants exactly as
printed, cancels their near-common pole/zero pairs (eq. 12 has a pole at z = 1 cancelled by
a zero at z = 1; left in, the closed-loop DC gain comes out as zero), and closes a discrete
LQR state-feedback loop on the minimal realisation, with a reference gain so that the
closed loop from the ballast input to the output has a chosen DC gain.

The "ballast input" identified by the U-model is the reference of this inner loop, in model
units (−2..2 full scale, as in the paper's experiment); the plant's own input (ballast
rate) is internal to the vehicle.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import control
import numpy as np
from numpy.typing import NDArray

from protocols.keys import CHANNELS  # the one list; the emulator's modules import it from here

Array = NDArray[np.float64]

#: Paper eq. 12, ballast rate → depth, coefficients in descending powers of z.
DEPTH_NUM = (-0.662, 1.327, -0.665, 0.0)
DEPTH_DEN = (1.0, -2.02, 0.063, 1.934, -0.977)

#: Paper eq. 13, ballast rate → pitch, coefficients in descending powers of z.
PITCH_NUM = (10.1, 21.94, 0.0, 16.84, -21.7, 9.56, 0.0)
PITCH_DEN = (1.0, -1.95, 1.083, -1.17, 1.69, -0.37, -0.33, 0.05)


def cancel_common_roots(
    num: tuple[float, ...] | Array, den: tuple[float, ...] | Array, tol: float = 1e-4
) -> tuple[Array, Array]:
    """Remove pole/zero pairs closer than ``tol`` and return the reduced (num, den).

    The gain is preserved by keeping the leading coefficients' ratio; each zero cancels at
    most one pole (the nearest).
    """
    num_arr = np.trim_zeros(np.asarray(num, dtype=float), "f")
    den_arr = np.trim_zeros(np.asarray(den, dtype=float), "f")
    zeros = list(np.roots(num_arr))
    poles = list(np.roots(den_arr))
    kept_zeros = []
    for z in zeros:
        if not poles:
            kept_zeros.append(z)
            continue
        distances = [abs(z - p) for p in poles]
        nearest = int(np.argmin(distances))
        if distances[nearest] < tol:
            poles.pop(nearest)
        else:
            kept_zeros.append(z)
    gain = num_arr[0] / den_arr[0]
    new_num = gain * np.real_if_close(np.poly(kept_zeros), tol=1e6).real
    new_den = np.real_if_close(np.poly(poles), tol=1e6).real
    return np.atleast_1d(new_num), np.atleast_1d(new_den)


def open_loop_plant(channel: str, dt: float = 1.0) -> control.StateSpace:
    """The paper's plant for ``channel`` as a minimal discrete state-space model."""
    if channel == "depth":
        num, den = cancel_common_roots(DEPTH_NUM, DEPTH_DEN)
    elif channel == "pitch":
        num, den = cancel_common_roots(PITCH_NUM, PITCH_DEN)
    else:
        raise ValueError(f"unknown channel {channel!r}; expected one of {CHANNELS}")
    return control.tf2ss(control.tf(num, den, dt))


@dataclass(frozen=True)
class InnerLoopDesign:
    """LQR weights and the DC gain the closed loop is scaled to, per channel.

    ``q_output`` weighs y² and ``r_input`` the plant input (ballast rate) in the LQR cost;
    ``q_state`` is a small identity weight that keeps the Riccati equation well posed.
    ``dc_gain`` is output units per unit of ballast input (m for depth, rad for pitch).
    """

    q_output: float
    r_input: float
    q_state: float = 1e-6
    dc_gain: float = 1.0


DEFAULT_DESIGNS = {
    "depth": InnerLoopDesign(q_output=10.0, r_input=1.0, dc_gain=2.5),
    "pitch": InnerLoopDesign(q_output=1.0, r_input=1.0, dc_gain=0.2),
}


@dataclass
class ClosedLoopChannel:
    """One stabilised channel: x⁺ = (A − BK)x + B·N·r, y = Cx + D(−Kx + N·r).

    ``step`` is the hot path of the emulator and the in-process experiment, so it works on
    plain numpy arrays rather than python-control objects.
    """

    channel: str
    dt: float
    a_cl: Array
    b_cl: Array
    c_cl: Array
    d_cl: float
    gain_k: Array
    ref_gain: float
    state: Array = field(init=False)

    def __post_init__(self) -> None:
        self.state = np.zeros(self.a_cl.shape[0])

    def reset(self) -> None:
        self.state = np.zeros(self.a_cl.shape[0])

    def output(self, reference: float) -> float:
        """Output for the current state if ``reference`` is applied now."""
        return float(self.c_cl.dot(self.state) + self.d_cl * reference)

    def step(self, reference: float) -> float:
        """Apply ``reference`` for one period; return the output at the start of the period.

        The same products (BLAS, with fused multiply-adds) and sums as ``c @ x + d·r`` and
        ``A @ x + b·r``: ``ndarray.dot`` calls the same routines as ``@`` with less dispatch,
        and the new state is summed in place.
        """
        state = self.state
        y = float(self.c_cl.dot(state) + self.d_cl * reference)
        state = self.a_cl.dot(state)
        state += self.b_cl * reference
        self.state = state
        return y

    def spectral_radius(self) -> float:
        return float(np.max(np.abs(np.linalg.eigvals(self.a_cl))))

    def dc_gain(self) -> float:
        n = self.a_cl.shape[0]
        return float(self.c_cl @ np.linalg.solve(np.eye(n) - self.a_cl, self.b_cl) + self.d_cl)

    def as_state_space(self) -> control.StateSpace:
        return control.ss(
            self.a_cl, self.b_cl.reshape(-1, 1), self.c_cl.reshape(1, -1), self.d_cl, self.dt
        )


def design_closed_loop(
    channel: str, dt: float = 1.0, design: InnerLoopDesign | None = None
) -> ClosedLoopChannel:
    """Design the LQR inner loop for ``channel`` and verify it is stable.

    Raises ``RuntimeError`` when the closed loop is not strictly inside the unit circle,
    so an emulator can never run an unstable inner loop silently.
    """
    design = design or DEFAULT_DESIGNS[channel]
    plant = open_loop_plant(channel, dt)
    a = np.asarray(plant.A, dtype=float)
    b = np.asarray(plant.B, dtype=float)
    c = np.asarray(plant.C, dtype=float)
    d = float(np.asarray(plant.D, dtype=float).item())
    n = a.shape[0]
    q = design.q_output * (c.T @ c) + design.q_state * np.eye(n)
    r = np.array([[design.r_input]])
    gain_k, _, _ = control.dlqr(a, b, q, r)
    gain_k = np.asarray(gain_k, dtype=float)
    a_cl = a - b @ gain_k
    c_cl = (c - d * gain_k).ravel()
    b_unit = b.ravel()
    unit_dc = float(c_cl @ np.linalg.solve(np.eye(n) - a_cl, b_unit) + d)
    if abs(unit_dc) < 1e-12:
        raise RuntimeError(f"{channel}: closed loop has zero DC gain; cannot scale reference")
    ref_gain = design.dc_gain / unit_dc
    loop = ClosedLoopChannel(
        channel=channel,
        dt=dt,
        a_cl=a_cl,
        b_cl=b_unit * ref_gain,
        c_cl=c_cl,
        d_cl=d * ref_gain,
        gain_k=gain_k.ravel(),
        ref_gain=ref_gain,
    )
    radius = loop.spectral_radius()
    if not radius < 1.0:
        raise RuntimeError(f"{channel}: inner loop not stable (spectral radius {radius:.6f})")
    return loop
