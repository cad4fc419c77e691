"""The servo's state of the day: session terms read from a sample file itself.

Each recording session (a real file, a simulated arm) has its own servo state: supply
voltage, winding temperature and wear change how much motor torque one tick of position
error buys. On the real OpenMANIPULATOR-X files the slope of the joint torque against the
discrepancy differs between sessions (joint 2: 22.0 N m/rad on cube's file, 20.1 on
white's), and the slope of the servo's own Present Current against the discrepancy moves
with it (18.3 against 17.5): the position loop turns the error into PWM, the winding turns
PWM into current and the current into torque, so a change of voltage or resistance scales
the current and the torque alike. That slope needs no ground truth: it is measured on the
unknown object's own samples.

The real servo's current is not linear in the discrepancy near zero: within about +-1 to
+-3 ticks of error it reads no current at all (the drive's dead band), then grows by the
gain per tick. A straight line through every sample is therefore flatter where more
samples sit near zero error, that is, on a lighter load: on the two real files its joint 4
"gain" differs by 28 % (5.12 against 6.56 N m/rad) while the servo, compared at the same
current, is the same (docs/results.md). The gain is therefore fitted beyond a dead band,
``current = g * sign(e) * max(|e| - d, 0) + c``, with ``d`` chosen per joint by least
squares over a grid: a servo's property, not its load's.

A model folder records the current gain of the data it was trained on (its reference); a
file of another session is read as if recorded in the reference session by rescaling its
discrepancy per joint, ``e' = e (g_file / g_ref) ** strength`` (``strength`` 1: the
current tracks the torque fully; 0: no adaptation). :func:`adapt` does it on a
:class:`~jaxinertia.samples.Samples` record, so training, evaluation and estimation see one
door, and everything past it (networks, baselines) is unchanged.

Where the samples carry the servos' own Present Input Voltage and Present Temperature (the
fields ``voltage`` [V] and ``temperature`` [deg C] of ``jaxinertia collect``'s files), the
session records them too, and so does a model folder trained on such files:
:func:`servo_state_change` compares a file's with the folder's. They are reported, not
used to rescale: at rest the torque per tick is ``k_t KP e V / (885 R)``, so the supply
``V`` moves the current and the torque alike and the current gain already carries it
(rescaling by the voltage as well would count it twice); the winding's temperature moves
``R`` (seen by the current) and ``k_t`` (not seen), by a law no real file here can check
(the authors' files record neither).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from flax import struct

from jaxinertia.errors import UsageError
from jaxinertia.fileio import nan_to_null, null_to_nan
from jaxinertia.samples import Samples

__all__ = ["DEAD_BAND_GRID", "ServoSession", "SessionReference", "adapt", "adapt_objects",
           "dead_band_fit", "seen_dead_band", "servo_session", "servo_state_change",
           "session_reference"]


@struct.dataclass
class ServoSession:
    """Per-joint (N,) servo terms of one session, from its at-rest samples alone."""

    #: Slope of the current torque (k_t * Present Current) against the discrepancy q_d - q,
    #: per joint, fitted with an intercept over every sample [N m/rad].
    current_gain: np.ndarray
    #: Its standard error [N m/rad].
    current_gain_se: np.ndarray
    n_samples: int = struct.field(pytree_node=False, default=0)
    #: The dead band fitted with it, per joint [rad] (None: not fitted).
    dead_band: np.ndarray | None = None
    #: Each servo's Present Input Voltage, the median over the samples [V] (None: the
    #: samples do not record it, as the authors' files do not).
    supply_voltage: np.ndarray | None = None
    #: Each servo's Present Temperature, the median over the samples [deg C] (None: not
    #: recorded).
    temperature: np.ndarray | None = None

    def to_dict(self) -> dict:
        """Plain data (a joint without a current sensor: null gain and standard error)."""
        se = np.where(np.isfinite(self.current_gain), self.current_gain_se, np.nan)
        d = {"current_gain": nan_to_null(self.current_gain),
             "current_gain_se": nan_to_null(se), "n_samples": self.n_samples}
        if self.dead_band is not None:
            d["dead_band"] = nan_to_null(self.dead_band)
        return {**d, **_servo_state_dict(self)}


def _servo_state_dict(terms) -> dict:
    """The recorded supply and temperature of ``terms`` (a session or a reference), where
    known."""
    return {k: nan_to_null(v) for k in ("supply_voltage", "temperature")
            if (v := getattr(terms, k)) is not None}


def _recorded(parts: Sequence[Samples], field: str) -> np.ndarray | None:
    """Per joint, the median of the samples' ``field`` (``extra``: what ``collect``
    recorded with each sample), pooled over ``parts``; None unless every part has it."""
    if not parts or not all(field in p.extra for p in parts):
        return None
    values = np.concatenate([np.asarray(p.extra[field], np.float64).reshape(p.n_samples, -1)
                             for p in parts])
    if values.shape[1] != parts[0].n_joints or not np.isfinite(values).all():
        return None
    return np.median(values, axis=0)


#: The dead bands tried [rad]: 0 to 5 ticks of a 4096-tick servo in tenths of a tick (the
#: real XM430s of the OpenMANIPULATOR-X: 0.7-3 ticks).
DEAD_BAND_GRID = np.arange(51) * 0.1 * (2.0 * np.pi / 4096)


def dead_band_fit(e: np.ndarray, current: np.ndarray, grid: np.ndarray = DEAD_BAND_GRID):
    """Per joint, the least-squares fit of ``current = g * sign(e) max(|e| - d, 0) + c``
    over the dead bands ``d`` of ``grid``. ``e``, ``current``: (S, N). Returns ``(g, se,
    d)``, each (N,): the gain, its standard error (given ``d``) and the dead band; a joint
    without a current sensor (a non-finite current) gets gain and dead band NaN, standard
    error inf (:meth:`SessionReference.ratio` leaves it as it is)."""
    e, current = np.asarray(e, np.float64), np.asarray(current, np.float64)
    sensed = np.all(np.isfinite(current), axis=0)  # (N,)
    current = np.where(sensed, current, 0.0)
    S = e.shape[0]
    x = np.sign(e)[None] * np.maximum(np.abs(e)[None] - grid[:, None, None], 0.0)  # (D, S, N)
    xc = x - x.mean(axis=1, keepdims=True)
    yc = current - current.mean(axis=0)
    sxx = np.sum(xc * xc, axis=1)  # (D, N)
    sxy = np.sum(xc * yc[None], axis=1)
    safe = np.where(sxx > 0, sxx, 1.0)
    sse = np.where(sxx > 0, np.sum(yc * yc, axis=0)[None] - sxy ** 2 / safe, np.inf)
    best = np.argmin(sse, axis=0)  # (N,) the first of equals: the smallest dead band
    cols = np.arange(e.shape[1])
    ok = sensed & (sxx[best, cols] > 0)
    gain = np.where(ok, sxy[best, cols] / safe[best, cols], np.where(sensed, 0.0, np.nan))
    dof = max(S - 2, 1)
    se = np.where(ok, np.sqrt(np.maximum(sse[best, cols], 0.0) / dof / safe[best, cols]),
                  np.inf)
    return gain, se, np.where(sensed, np.asarray(grid)[best], np.nan)


#: A joint's dead band is seen only where its error takes both signs, each on at least this
#: share of the samples (joint 2 of the OpenMANIPULATOR-X carries the arm and never does).
MIN_SIGN_SHARE = 0.1


def seen_dead_band(data: Samples | Sequence[Samples]) -> np.ndarray:
    """(N,) the dead band [rad] of the records' Present Current, pooled
    (:func:`dead_band_fit`); 0 where it cannot be seen: a joint whose error keeps one sign
    (there ``d`` trades against the offset ``c``) or one without a current sensor. The
    simulator's reading takes it (``sim.real_fit.fit_servo_friction(dead_band=True)``)."""
    parts = [data] if isinstance(data, Samples) else list(data)
    e = np.concatenate([np.asarray(p.q_d, np.float64) - np.asarray(p.q, np.float64)
                        for p in parts])
    _, _, band = dead_band_fit(e, np.concatenate([np.asarray(p.current_tau, np.float64)
                                                  for p in parts]))
    seen = np.minimum(np.mean(e > 0, axis=0), np.mean(e < 0, axis=0)) >= MIN_SIGN_SHARE
    return np.where(seen & np.isfinite(band), band, 0.0)


def servo_session(data: Samples | Sequence[Samples]) -> ServoSession:
    """The session terms of one session's samples (several records: pooled): per joint the
    current gain beyond the dead band (:func:`dead_band_fit`), and the servos' supply and
    temperature where every record carries them."""
    parts = [data] if isinstance(data, Samples) else list(data)
    e = np.concatenate([np.asarray(p.q_d, np.float64) - np.asarray(p.q, np.float64)
                        for p in parts])
    cur = np.concatenate([np.asarray(p.current_tau, np.float64) for p in parts])
    gain, se, dead = dead_band_fit(e, cur)
    return ServoSession(gain, se, n_samples=int(e.shape[0]), dead_band=dead,
                        supply_voltage=_recorded(parts, "voltage"),
                        temperature=_recorded(parts, "temperature"))


#: A session's current gain is used only where its standard error is below this share
#: of it (a real file of 1000 samples: 0.3-2 %; 64 samples: 2-8 %).
MAX_RELATIVE_SE = 0.1
#: Ratios beyond this range are not a servo's day but another servo or a broken reading;
#: they are clipped to it (the answer records the ratio that was used).
RATIO_RANGE = (0.7, 1.4)


@struct.dataclass
class SessionReference:
    """What a model folder records: the current gain of its training session(s) and how
    strongly a new session's discrepancy is rescaled towards it."""

    current_gain: np.ndarray  # (N,) [N m/rad]
    strength: float = struct.field(pytree_node=False, default=1.0)
    #: The training session's supply and temperature per joint, where its files recorded
    #: them (:class:`ServoSession`); reported beside a new file's, never used to rescale.
    supply_voltage: np.ndarray | None = None  # (N,) [V]
    temperature: np.ndarray | None = None  # (N,) [deg C]

    @classmethod
    def of(cls, session: ServoSession, strength: float = 1.0) -> SessionReference:
        """The reference that ``session`` (a model's training session) makes."""
        return cls(session.current_gain, float(strength), session.supply_voltage,
                   session.temperature)

    def gain_ratio(self, session: ServoSession) -> np.ndarray:
        """(N,) ``g / g_ref``, the session's current gain over the reference's; NaN for a
        joint whose current does not follow its discrepancy (no spread, a dead current
        reading, too few samples to tell the slope within :data:`MAX_RELATIVE_SE`)."""
        g, g_ref = np.asarray(session.current_gain), np.asarray(self.current_gain)
        if g.shape != g_ref.shape:
            raise UsageError(f"session terms of {g.shape[0]} joints against a reference of "
                             f"{g_ref.shape[0]}")
        se = np.asarray(session.current_gain_se)
        ok = (g > 0) & (g_ref > 0) & np.isfinite(g) & (se < MAX_RELATIVE_SE * np.abs(g))
        return np.where(ok, np.abs(g / np.where(ok, g_ref, 1.0)), np.nan)

    def ratio(self, session: ServoSession) -> np.ndarray:
        """(N,) the factor on a session's discrepancy, ``(g / g_ref) ** strength``
        (:meth:`gain_ratio` clipped to :data:`RATIO_RANGE`; a joint without one is left as
        it is)."""
        raw = self.gain_ratio(session)
        ok = np.isfinite(raw)
        return np.where(ok, np.clip(np.where(ok, raw, 1.0), *RATIO_RANGE) ** self.strength,
                        1.0)

    def to_dict(self) -> dict:
        """Plain data (a joint without a current sensor: null gain, left as it is)."""
        return {"current_gain": nan_to_null(self.current_gain),
                "strength": float(self.strength), **_servo_state_dict(self)}

    @classmethod
    def from_dict(cls, d: dict | None) -> SessionReference | None:
        if not d:
            return None
        state = {k: null_to_nan(d[k]) for k in ("supply_voltage", "temperature")
                 if d.get(k) is not None}
        return cls(null_to_nan(d["current_gain"]), float(d.get("strength", 1.0)), **state)


def adapt(data: Samples, reference: SessionReference | None,
          session: ServoSession | None = None) -> tuple[Samples, np.ndarray]:
    """``data`` read as if recorded in the reference session: its discrepancy rescaled per
    joint by ``reference.ratio(session)`` (``session``: measured on ``data`` when not
    given). Returns the record and the (N,) ratio; no reference: unchanged, ratio 1."""
    if reference is None or reference.strength == 0.0:
        return data, np.ones(data.n_joints)
    ratio = reference.ratio(session if session is not None else servo_session(data))
    q = np.asarray(data.q)
    q_d = q + (np.asarray(data.q_d) - q) * ratio.astype(q.dtype)
    return data.replace(q_d=q_d), ratio


def session_reference(config: dict, strength: float | None = None, *,
                      simulated: bool = False) -> SessionReference | None:
    """A model folder's session reference (from its ``config``) for real files (None: the
    folder predates sessions), or, ``simulated``, for simulated ones: the session of the
    simulator that made its training data (real ones' when it has none); ``strength``
    overrides the recorded one."""
    ref = SessionReference.from_dict(config.get("session"))
    if simulated:
        ref = SessionReference.from_dict(config.get("simulator_session")) or ref
    return ref if ref is None or strength is None else ref.replace(strength=float(strength))


def adapt_objects(objects: Sequence[Samples], reference: SessionReference | None
                  ) -> tuple[list[Samples], list[list[float]]]:
    """Each object's samples (one recording session each) read in the reference session,
    from its own current-discrepancy slope; returns them and the per-joint ratios."""
    pairs = [adapt(o, reference) for o in objects]
    return [p[0] for p in pairs], [p[1].tolist() for p in pairs]


def servo_state_change(reference: SessionReference | None, session: ServoSession) -> dict:
    """How a file's servo state (``session``) stands against a model folder's
    (``reference``), per joint: the file's supply [V] and temperature [deg C] where it
    recorded them, the reference's where it did, and where both did, the supply's ratio
    (file / reference: at rest the torque per tick scales by it, and so does the current,
    so the current gain's ratio should show it too) and the temperature's difference [K].
    Also the current gain's ratio (file / reference) where both are known, adaptation or
    not."""
    out: dict = {k: None for k in ("supply_voltage", "temperature", "reference_supply_voltage",
                                   "reference_temperature", "supply_ratio",
                                   "temperature_change", "current_gain_ratio")}
    for k in ("supply_voltage", "temperature"):
        mine = getattr(session, k)
        theirs = None if reference is None else getattr(reference, k)
        out[k] = None if mine is None else nan_to_null(mine)
        out["reference_" + k] = None if theirs is None else nan_to_null(theirs)
        if mine is not None and theirs is not None and np.shape(mine) == np.shape(theirs):
            change = (np.asarray(mine) / np.asarray(theirs) if k == "supply_voltage"
                      else np.asarray(mine) - np.asarray(theirs))
            out["supply_ratio" if k == "supply_voltage" else "temperature_change"] = \
                nan_to_null(change)
    if reference is not None and np.shape(reference.current_gain) == np.shape(
            session.current_gain):
        out["current_gain_ratio"] = nan_to_null(reference.gain_ratio(session))
    return out
