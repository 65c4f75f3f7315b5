"""Message models of the streaming service (docs/design.md §7).

Every message is a pydantic v2 model with ``schema_name`` and ``schema_version``. Array fields hold
numpy arrays in Python; on the wire (``services.wire``) each array travels as a raw little-endian
buffer and the JSON header holds, in the array field's place, the *name* of its buffer: the dotted
field path (``"rf"``, ``"probe.positions"``, ``"grid.x"``), described in the header's ``arrays`` list
by an :class:`ArrayDescriptor` (name, dtype, shape, offset, nbytes).

Array fields are declared as ``Annotated[np.ndarray, ArraySpec(...)]`` (``services.arrays``). Built in
Python, an array of another dtype is cast only when the cast is safe (float32 → float64 positions);
otherwise, and always when decoding, the dtype must be one the field allows. Big-endian inputs are
converted to little-endian at construction.

Versioning: ``schema_version`` is ``"MAJOR.MINOR"``. A reader accepts any minor version of its major
(minor versions only add optional fields; unknown header fields are ignored) and refuses another
major.

Units are SI throughout: metres, seconds, hertz, m/s.
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, JsonValue, ModelWrapValidatorHandler, PrivateAttr, model_validator

from services.arrays import ArrayFieldError, array_field

if TYPE_CHECKING:  # pragma: no cover
    from fpcore.acquisition import Acquisition
    from fpcore.grid import Grid as CoreGrid

__all__ = [
    "ConfocalImage",
    "Detection",
    "Detections",
    "ErrorReport",
    "GammaMap",
    "Grid",
    "Latency",
    "MESSAGE_TYPES",
    "Message",
    "Normalisation",
    "Probe",
    "RFFrame",
    "Status",
    "Track",
    "Tracks",
    "UINT16_MAX",
    "VERSION_PATTERN",
    "examples",
]

VERSION_PATTERN = r"^[0-9]+\.[0-9]+$"
Vec3 = tuple[float, float, float]
#: the processor's --union: the two maps of a frame, as recorded and weighted by its own 1/v(t) (docs/design.md §4.14)
Statistic = Literal["as recorded", "weighted"]
#: Largest physical RF amplitude a frame may carry: ``fpcore.budget.MAX_RF_ABS`` (float32 spectra and
#: energies overflow beyond it), repeated here so that decoding never imports fpcore (tests/test_wire.py).
MAX_RF_ABS = 1e12


_AXIS = array_field("<f8", ndim=1, finite=True, min_size=1)


class _Model(BaseModel):
    model_config = ConfigDict(
        extra="ignore", allow_inf_nan=False, validate_assignment=True, arbitrary_types_allowed=False
    )


class Message(_Model):
    """Base of every wire message."""

    schema_name: str
    schema_version: str = Field(default="1.0", pattern=VERSION_PATTERN, description="MAJOR.MINOR.")

    @classmethod
    def __pydantic_init_subclass__(cls, **kwargs: Any) -> None:
        super().__pydantic_init_subclass__(**kwargs)
        if "arrays" in cls.model_fields:
            raise TypeError(f"{cls.__name__}: 'arrays' is reserved for the wire header's buffer list")

    @classmethod
    def version(cls) -> tuple[int, int]:
        """(major, minor) this code writes; it reads any minor of the same major."""
        major, minor = str(cls.model_fields["schema_version"].default).split(".")
        return int(major), int(minor)

    def for_wire(self) -> Message:
        """The message as it travels (``services.wire.encode`` writes this): itself, or for a lossy
        encoding (:class:`GammaMap`, :class:`ConfocalImage` 1.1) a copy holding the integer codes."""
        return self


# ---------------------------------------------------------------------------------------------- parts


class Probe(_Model):
    """Transducer array: element centres (N_u, 3) in metres (linear arrays have y = 0)."""

    positions: Annotated[np.ndarray, array_field("<f8", ndim=2, trailing=(3,), finite=True, min_size=3)]
    pitch: float = Field(gt=0, description="Element pitch, m.")
    centre_frequency: float = Field(gt=0, description="Hz.")
    bandwidth: float = Field(gt=0, description="Full -6 dB bandwidth, Hz.")

    @property
    def n_elements(self) -> int:
        return int(self.positions.shape[0])


class Grid(_Model):
    """Imaging grid axes in metres; ``y`` is None for a 2D (x–z) grid. Arrays on the grid have shape
    (N_x, N_z) in 2D and (N_x, N_y, N_z) in 3D (fpcore.grid.Grid convention)."""

    x: Annotated[np.ndarray, _AXIS]
    y: Annotated[np.ndarray, _AXIS] | None = None
    z: Annotated[np.ndarray, _AXIS]

    @property
    def shape(self) -> tuple[int, ...]:
        axes = (self.x, self.z) if self.y is None else (self.x, self.y, self.z)
        return tuple(int(a.size) for a in axes)

    @classmethod
    def from_grid(cls, grid: CoreGrid) -> Grid:
        """From an ``fpcore.grid.Grid``."""
        return cls(x=grid.x, y=grid.y, z=grid.z)

    def to_grid(self) -> CoreGrid:
        """As an ``fpcore.grid.Grid``."""
        from fpcore.grid import Grid as CoreGrid

        return CoreGrid(self.x, self.z, self.y)


def nonfinite_path(value: Any, path: str) -> str | None:
    """'truth.targets[0].position_m[2]: expected a finite number, got inf' for the first NaN/inf in a JSON
    value (None when every number is finite)."""
    if isinstance(value, float) and not math.isfinite(value):
        return f"{path}: expected a finite number, got {value}"
    if isinstance(value, dict):
        return next((p for k, v in value.items() if (p := nonfinite_path(v, f"{path}.{k}"))), None)
    if isinstance(value, (list, tuple)):
        return next((p for i, v in enumerate(value) if (p := nonfinite_path(v, f"{path}[{i}]"))), None)
    return None


#: largest code of a uint16-quantised map (GammaMap, ConfocalImage 1.1).
UINT16_MAX = 65535
#: largest level (dB) a linear float32 value can have (10·log10 of float32's maximum, ≈ 385.3 dB).
_F32_MAX = float(np.finfo(np.float32).max)
_F32_TOP_DB = 10 * math.log10(_F32_MAX)


def _hold(model: BaseModel, name: str, value: Any) -> None:
    """Set a field from a validator without re-running validation (validate_assignment would recurse)."""
    model.__dict__[name] = value


def quantise_linear(values: np.ndarray, step: float) -> np.ndarray:
    """uint16 codes round(values / step), clipped to 0…65535 (GammaMap 1.1)."""
    q = np.rint(np.asarray(values, np.float64) / step)
    return np.clip(q, 0, UINT16_MAX).astype(np.uint16)


def dequantise_linear(codes: np.ndarray, step: float) -> np.ndarray:
    """float32 codes × step (read-only, like a decoded buffer)."""
    if codes.size and int(np.max(codes)) * step > _F32_MAX:
        raise ArrayFieldError("gamma_step", f"expected code × step within float32, got gamma_step {step:.6g}")
    out = np.multiply(codes, np.float32(step), dtype=np.float32)  # codes are exact in float32
    out.flags.writeable = False
    return out


def _levels(values: np.ndarray, scale: str) -> np.ndarray:
    """Level in dB (float64): 10·log10(value) for a linear image (−inf at 0), the value for a dB image."""
    v = np.asarray(values, np.float64)
    if scale == "db":
        return v
    with np.errstate(divide="ignore"):
        return 10.0 * np.log10(v)


def _top_level(values: np.ndarray, scale: str) -> float:
    """The image's largest level in dB (0 for an all-zero linear image); refuses a negative linear value."""
    if scale == "linear":
        lo, hi = float(np.min(values)), float(np.max(values))
        if lo < 0:
            raise ArrayFieldError("image", f"expected a linear image ≥ 0 to travel as dB codes, got {lo:.3g}")
        return 10.0 * math.log10(hi) if hi > 0 else 0.0
    return float(np.max(values))


def quantise_db(values: np.ndarray, step: float, floor: float, scale: str) -> np.ndarray:
    """uint16 codes round((L − floor) / step), clipped to 0…65535, of the image's level L in dB."""
    q = np.rint((_levels(values, scale) - floor) / step)
    return np.clip(np.nan_to_num(q, nan=0.0, neginf=0.0), 0, UINT16_MAX).astype(np.uint16)


def dequantise_db(codes: np.ndarray, step: float, floor: float, scale: str) -> np.ndarray:
    """float32 image (read-only) from dB codes: L = floor + code × step; linear: 10^(L/10), and 0 for code 0."""
    if codes.size and floor + int(np.max(codes)) * step > _F32_TOP_DB and scale == "linear":
        raise ArrayFieldError("db_floor", f"expected levels ≤ {_F32_TOP_DB:.1f} dB (float32), got db_floor {floor:.6g}")
    level = floor + codes * np.float64(step)
    if scale == "linear":
        level = np.where(codes == 0, 0.0, 10.0 ** (level / 10.0))
    out = level.astype(np.float32)
    out.flags.writeable = False
    return out


def _check_on_grid(field: str, arr: np.ndarray, grid: Grid) -> None:
    if tuple(arr.shape) != grid.shape:
        raise ArrayFieldError(field, f"expected the grid's shape {grid.shape}, got {tuple(arr.shape)}")


class Normalisation(_Model):
    """How γ was normalised. ``cauchy_schwarz``: γ = |Σ_f Tr R F†| / √(Σ_f‖R‖_F² Σ_f‖F‖_F²) (docs/design.md §4.7),
    so 0 ≤ γ ≤ 1."""

    kind: str = "cauchy_schwarz"
    band_hz: tuple[float, float] | None = Field(default=None, description="Band [f-, f+] used, Hz.")
    r_energy: float | None = Field(default=None, ge=0, description="Σ_f ‖R(f)‖_F².")
    f_energy: float | None = Field(default=None, ge=0, description="Σ_f ‖F(q,f)‖_F².")
    gamma_m: float | None = Field(default=None, ge=0, description="γ_M = √⟨γ²⟩ over the map.")


class Detection(_Model):
    """One detected target."""

    fingerprint: str = Field(description="Name of the fingerprint (dictionary entry) that matched.")
    state: dict[str, float] = Field(default_factory=dict, description="Dictionary state q of the match.")
    position_m: Vec3 = Field(description="[x, y, z], m.")
    gamma_max: float = Field(ge=0, description="Peak likelihood index γ (≤ 1).")
    contrast_c_gamma: float = Field(ge=0, description="C_γ = γ(target) / mean γ outside the target.")
    contrast_c: float = Field(ge=0, description="C = (γ_max/γ_M)², γ_M = √⟨γ²⟩ over the map (the paper's S6 C).")
    contrast_local: float | None = Field(
        default=None,
        ge=0,
        description="γ/γ_M(r) against the local null level at the peak "
        "(the contrast the PFA is computed from; schema 1.1).",
    )
    pfa: float = Field(
        ge=0,
        le=1,
        description="Calibrated false-alarm probability: that target-free γ reaches "
        "this local contrast anywhere in the searched region "
        "(docs/design.md §4.9).",
    )
    precision_m: tuple[float, float] = Field(description="Cramér–Rao precision [lateral, axial], m.")
    truth_error_m: float | None = Field(default=None, ge=0, description="Distance to ground truth, m.")
    velocity_m_s: Vec3 | None = Field(
        default=None,
        description="[v_x, v_y, v_z], m/s: the velocity dictionary's estimate around this detection (the argmax "
        "of γ over position and velocity; docs/design.md §4.13). None: the fingerprint has no velocity "
        "grid, or the frame no PRF (schema 1.2).",
    )
    velocity_sigma_m_s: Vec3 | None = Field(
        default=None, description="σ of velocity_m_s per axis (step/√12; 0: axis not searched), m/s (schema 1.2)."
    )
    velocity_position_m: Vec3 | None = Field(
        default=None,
        description="[x, y, z], m: the peak of the motion-aware γ at velocity_m_s (the position at the middle "
        "of the transmit sequence; schema 1.2).",
    )
    velocity_gamma: float | None = Field(
        default=None, ge=0, description="γ of the motion-aware fingerprint at that peak (schema 1.2)."
    )
    velocity_states: int | None = Field(
        default=None, ge=1, description="Number of velocities searched (the look-elsewhere factor; schema 1.2)."
    )
    statistic: Statistic | None = Field(
        default=None,
        description="With the processor's --union: the map this detection was found on, the frame 'as recorded' or "
        "'weighted' by its own 1/v(t); its pfa is then twice that map's own (docs/design.md §4.14, eq. W2). "
        "None: one statistic (schema 1.3).",
    )

    @model_validator(mode="after")
    def _check(self) -> Detection:
        if min(self.precision_m) < 0:
            raise ArrayFieldError("precision_m", f"expected non-negative values, got {self.precision_m}")
        if self.velocity_sigma_m_s is not None and min(self.velocity_sigma_m_s) < 0:
            raise ArrayFieldError("velocity_sigma_m_s", f"expected non-negative values, got {self.velocity_sigma_m_s}")
        return self


class Track(_Model):
    """One track. ``covariance`` is the 3×3 position covariance (m²), symmetric."""

    id: int = Field(ge=0)
    fingerprint: str = Field(default="", description="Name of the fingerprint whose γ-map the track follows.")
    position_m: Vec3
    velocity_m_s: Vec3
    covariance: tuple[Vec3, Vec3, Vec3]
    confidence: float = Field(ge=0, le=1)
    age: int = Field(ge=0, description="Frames since the track started.")
    status: Literal["tentative", "confirmed", "coasting", "lost"] | None = Field(
        default=None, description="tentative → confirmed → coasting (no significant measurement) → lost (schema 1.1)."
    )
    pfa: float | None = Field(
        default=None, ge=0, le=1, description="Calibrated PFA of the last accepted measurement (schema 1.1)."
    )

    @model_validator(mode="after")
    def _check(self) -> Track:
        c = np.asarray(self.covariance)
        if np.any(np.diag(c) < 0):
            raise ArrayFieldError("covariance", "expected a non-negative diagonal")
        if np.max(np.abs(c - c.T)) > 1e-6 * max(float(np.max(np.abs(c))), 1e-300):
            raise ArrayFieldError("covariance", "expected a symmetric matrix")
        return self


class Latency(_Model):
    """Processing latency statistics, ms (None before the first frame)."""

    median: float | None = Field(default=None, ge=0)
    p95: float | None = Field(default=None, ge=0)


# ------------------------------------------------------------------------------------------- messages


class RFFrame(Message):
    """One plane-wave acquisition R(u_out, θ_in, t) (key ``fp/<rig>/rf``); sample n at t0 + n/fs.

    1.1 added ``prf`` (optional): without it (1.0 writers) the transmit times are unknown and the
    motion-aware fingerprints cannot be used. 1.2 added ``rf_scale`` (optional): int16 RF, as scanners
    deliver it, stands for ``rf × rf_scale`` (:meth:`to_acquisition` applies it; docs/wire.md)."""

    schema_name: Literal["RFFrame"] = "RFFrame"
    schema_version: str = Field(default="1.2", pattern=VERSION_PATTERN, description="MAJOR.MINOR.")
    frame_index: int = Field(ge=0)
    timestamp: float = Field(description="Acquisition time, s (source clock).")
    fs: float = Field(gt=0, description="Sampling frequency, Hz.")
    t0: float = Field(description="Time of the first sample, s.")
    c0: float = Field(gt=0, description="Sound speed, m/s.")
    probe: Probe
    sines: Annotated[np.ndarray, array_field("<f8", ndim=2, trailing=(2,), finite=True, min_size=2)] = Field(
        description="Transmit direction sines (N_θ, 2) = (s_x, s_y)."
    )
    rf: Annotated[np.ndarray, array_field("<f4", "<i2", ndim=3, finite=True, min_size=1)] = Field(
        description="RF data (N_u, N_θ, N_t), float32 or int16."
    )
    truth: dict[str, JsonValue] | None = Field(default=None, description="Ground truth (free JSON).")
    prf: float | None = Field(
        default=None,
        gt=0,
        description="Pulse repetition frequency, Hz: the transmits fire in "
        "order every 1/prf (None: unknown). Since 1.1.",
    )
    rf_scale: float | None = Field(
        default=None,
        gt=0,
        description="Physical value of one integer step of int16 RF (RF = rf × rf_scale; None: 1). "
        "Only with int16 RF. Since 1.2.",
    )

    _truth_problem: str | None = PrivateAttr(default=None)

    @model_validator(mode="wrap")
    @classmethod
    def _drop_broken_truth(cls, data: Any, handler: ModelWrapValidatorHandler[RFFrame]) -> RFFrame:
        """A truth with NaN or infinite numbers (e.g. 1e400) is dropped, not the frame: its RF is still good.
        What was wrong is kept in :attr:`truth_problem` for the receiver to report."""
        problem = None
        if isinstance(data, dict) and data.get("truth") is not None:
            problem = nonfinite_path(data["truth"], "truth")
            if problem is not None:
                data = {**data, "truth": None}
        frame = handler(data)
        if problem is not None:
            frame._truth_problem = problem
        return frame

    @property
    def truth_problem(self) -> str | None:
        """Why the sender's truth was dropped (None: kept, or there was none)."""
        return self._truth_problem

    @model_validator(mode="after")
    def _check(self) -> RFFrame:
        expected = (self.probe.n_elements, int(self.sines.shape[0]))
        if tuple(self.rf.shape[:2]) != expected:
            raise ArrayFieldError(
                "rf", f"expected shape (N_u={expected[0]}, N_θ={expected[1]}, N_t), got {tuple(self.rf.shape)}"
            )
        if np.any(np.sum(self.sines**2, axis=1) >= 1.0):
            raise ArrayFieldError("sines", "expected s_x² + s_y² < 1 for every transmit")
        if self.rf_scale is not None and self.rf.dtype != np.int16:
            raise ArrayFieldError("rf_scale", f"expected only with int16 RF, got RF of dtype {self.rf.dtype}")
        self._check_amplitude()
        return self

    def _check_amplitude(self) -> None:
        """max |rf| × (rf_scale or 1) ≤ :data:`MAX_RF_ABS` (the limit fpcore.budget puts on files)."""
        scale = 1.0 if self.rf_scale is None else self.rf_scale
        if self.rf.dtype == np.int16 and 32768.0 * scale <= MAX_RF_ABS:
            return  # no int16 sample can exceed it: no pass over the data
        peak = max(abs(float(np.max(self.rf))), abs(float(np.min(self.rf))))
        if peak * scale <= MAX_RF_ABS:
            return
        if self.rf_scale is None:
            raise ArrayFieldError(
                "rf", f"samples reach {peak:.3g}, above {MAX_RF_ABS:.0e}; expected values rescaled to a smaller unit"
            )
        raise ArrayFieldError(
            "rf_scale",
            f"expected at most {MAX_RF_ABS / peak:.3g} (samples reach {peak:.0f}, RF = rf × rf_scale ≤ "
            f"{MAX_RF_ABS:.0e}), got {self.rf_scale:.3g}",
        )

    @classmethod
    def from_acquisition(cls, acq: Acquisition) -> RFFrame:
        """From an ``fpcore.acquisition.Acquisition`` (arrays are shared, not copied)."""
        p = acq.probe
        return cls(
            frame_index=acq.frame_index,
            timestamp=acq.timestamp,
            fs=acq.fs,
            t0=acq.t0,
            c0=acq.c0,
            probe=Probe(
                positions=p.positions, pitch=p.pitch, centre_frequency=p.centre_frequency, bandwidth=p.bandwidth
            ),
            sines=acq.sequence.sines,
            rf=acq.rf,
            truth=dict(acq.truth) or None,
            prf=acq.sequence.prf,
        )

    def to_acquisition(self) -> Acquisition:
        """As an ``fpcore.acquisition.Acquisition`` (arrays are shared, not copied; int16 RF with an
        ``rf_scale`` becomes float32 RF × rf_scale)."""
        from fpcore.acquisition import Acquisition, PlaneWaveSequence
        from fpcore.acquisition import Probe as CoreProbe

        p = self.probe
        rf = self.rf if self.rf_scale is None else self.rf.astype(np.float32) * np.float32(self.rf_scale)
        return Acquisition(
            rf=rf,
            fs=self.fs,
            t0=self.t0,
            c0=self.c0,
            probe=CoreProbe(p.positions, p.pitch, p.centre_frequency, p.bandwidth),
            sequence=PlaneWaveSequence(self.sines, prf=self.prf),
            frame_index=self.frame_index,
            timestamp=self.timestamp,
            truth=dict(self.truth or {}),
        )


class GammaMap(Message):
    """Likelihood map/volume γ(r) of one fingerprint for one frame (key ``fp/<rig>/gamma``).

    1.1 added ``gamma_step`` (optional): with it, γ travels as uint16 codes q = round(γ / gamma_step), and
    γ = q × gamma_step (error ≤ gamma_step / 2; docs/wire.md). In Python ``gamma`` is always float32:
    built from uint16 codes (decoding) it holds their values; built from float32 with a step, it is
    quantised when encoded (:meth:`for_wire`). Without a step γ travels as float32 (1.0). 1.2 added the optional
    ``statistic``: with the processor's --union, which of the frame's two maps this is (eq. W2)."""

    schema_name: Literal["GammaMap"] = "GammaMap"
    schema_version: str = Field(default="1.2", pattern=VERSION_PATTERN, description="MAJOR.MINOR.")
    frame_index: int = Field(ge=0)
    timestamp: float = Field(description="Acquisition time of the input frame, s.")
    fingerprint: str
    state: dict[str, float] = Field(default_factory=dict, description="Dictionary state q.")
    grid: Grid
    gamma: Annotated[np.ndarray, array_field("<f4", "<u2", finite=True)] = Field(
        description="γ on the grid: float32, or uint16 codes with ``gamma_step`` (γ = gamma × gamma_step)."
    )
    normalisation: Normalisation = Field(default_factory=Normalisation)
    gamma_step: float | None = Field(
        default=None,
        gt=0,
        description="γ value of one uint16 code: γ travels as codes round(γ / gamma_step) (error ≤ "
        "gamma_step / 2); None: float32. Since 1.1.",
    )
    statistic: Statistic | None = Field(
        default=None,
        description="With the processor's --union: the map kept for this fingerprint, of the frame 'as recorded' or "
        "'weighted' by its own 1/v(t) (docs/design.md §4.14, eq. W2; the normalisation's r_energy is then the "
        "weighted frame's). None: one statistic. Since 1.2.",
    )

    @model_validator(mode="after")
    def _check(self) -> GammaMap:
        _check_on_grid("gamma", self.gamma, self.grid)
        step = self.gamma_step
        if self.gamma.dtype == np.uint16:
            if step is None:
                raise ArrayFieldError("gamma_step", "expected with uint16 γ (γ = gamma × gamma_step), got none")
            _hold(self, "gamma", dequantise_linear(self.gamma, step))
        elif step is not None and self.gamma.size:
            lo, hi = float(np.min(self.gamma)), float(np.max(self.gamma))
            if lo < 0:
                raise ArrayFieldError("gamma", f"expected γ ≥ 0 to travel as uint16 codes, got {lo:.3g}")
            if hi > (UINT16_MAX + 0.5) * step:
                raise ArrayFieldError(
                    "gamma_step", f"expected at least γ_max/{UINT16_MAX} = {hi / UINT16_MAX:.6g}, got {step:.6g}"
                )
        return self

    def for_wire(self) -> GammaMap:
        """The message as it travels: with ``gamma_step``, a copy holding the uint16 codes."""
        if self.gamma_step is None:
            return self
        return self.model_copy(update={"gamma": quantise_linear(self.gamma, self.gamma_step)})


class ConfocalImage(Message):
    """Confocal image |I(r)|² (linear) or in dB (key ``fp/<rig>/image``).

    1.1 added ``db_step`` and ``db_floor`` (optional): with them the image travels as uint16 codes of its
    level L in dB (L = 10·log10(value) for a linear image, the value itself in dB): q = round((L −
    db_floor) / db_step), clipped to 0…65535, and L = db_floor + q × db_step (error ≤ db_step / 2 in dB; a
    linear image's code 0 reads 0, a dB image's reads db_floor). In Python ``image`` is always float32 in
    its ``scale``, as for :class:`GammaMap`; built from float32 with a step and no floor, the floor is
    the image's maximum level − 65535 × db_step (nothing clips at the top)."""

    schema_name: Literal["ConfocalImage"] = "ConfocalImage"
    schema_version: str = Field(default="1.1", pattern=VERSION_PATTERN, description="MAJOR.MINOR.")
    frame_index: int = Field(ge=0)
    timestamp: float = Field(description="Acquisition time of the input frame, s.")
    grid: Grid
    image: Annotated[np.ndarray, array_field("<f4", "<u2", finite=True)] = Field(
        description="Image on the grid: float32, or uint16 codes of its level in dB with ``db_step`` and ``db_floor``."
    )
    scale: Literal["linear", "db"] = "linear"
    db_step: float | None = Field(
        default=None,
        gt=0,
        description="dB per uint16 code: the image travels as codes of its level in dB (error ≤ db_step / 2 dB); "
        "None: float32. Since 1.1.",
    )
    db_floor: float | None = Field(default=None, description="Level (dB) of code 0 of a uint16 image. Since 1.1.")

    @model_validator(mode="after")
    def _check(self) -> ConfocalImage:
        _check_on_grid("image", self.image, self.grid)
        step, floor = self.db_step, self.db_floor
        if self.image.dtype == np.uint16:
            if step is None or floor is None:
                missing = "db_step" if step is None else "db_floor"
                raise ArrayFieldError(missing, "expected with a uint16 image (level dB = db_floor + code × db_step)")
            _hold(self, "image", dequantise_db(self.image, step, floor, self.scale))
        elif floor is not None and step is None:
            raise ArrayFieldError("db_floor", "expected only with db_step")
        elif step is not None and self.image.size:
            top = _top_level(self.image, self.scale)
            if floor is None:
                _hold(self, "db_floor", top - UINT16_MAX * step)
            elif top > floor + (UINT16_MAX + 0.5) * step:
                raise ArrayFieldError(
                    "db_floor",
                    f"expected at least {top - UINT16_MAX * step:.6g} (top level {top:.6g} dB), got {floor:.6g}",
                )
        return self

    def for_wire(self) -> ConfocalImage:
        """The message as it travels: with ``db_step``, a copy holding the uint16 codes of the dB level."""
        if self.db_step is None or self.db_floor is None:
            return self
        return self.model_copy(update={"image": quantise_db(self.image, self.db_step, self.db_floor, self.scale)})


class Detections(Message):
    """Targets detected in one frame (key ``fp/<rig>/detections``). 1.1 added ``contrast_local``; 1.2 the
    optional velocity estimate of each detection (``velocity_m_s``, ``velocity_sigma_m_s``,
    ``velocity_position_m``, ``velocity_gamma``, ``velocity_states``); 1.3 the optional ``statistic`` (the map
    of the union, eq. W2)."""

    schema_name: Literal["Detections"] = "Detections"
    schema_version: str = Field(default="1.3", pattern=VERSION_PATTERN, description="MAJOR.MINOR.")
    frame_index: int = Field(ge=0)
    timestamp: float = Field(description="Acquisition time of the input frame, s.")
    detections: list[Detection] = Field(default_factory=list)


class Tracks(Message):
    """Active tracks after one frame (key ``fp/<rig>/tracks``)."""

    schema_name: Literal["Tracks"] = "Tracks"
    schema_version: str = Field(default="1.1", pattern=VERSION_PATTERN, description="MAJOR.MINOR.")
    frame_index: int = Field(ge=0)
    timestamp: float = Field(description="Acquisition time of the input frame, s.")
    tracks: list[Track] = Field(default_factory=list)


class Status(Message):
    """Periodic node status (key ``fp/<rig>/status``)."""

    schema_name: Literal["Status"] = "Status"
    node: str
    timestamp: float = Field(default_factory=time.time, description="Wall-clock time of the report, s.")
    frames_processed: int = Field(default=0, ge=0)
    frame_rate_hz: float = Field(default=0.0, ge=0)
    latency_ms: Latency = Field(default_factory=Latency)
    dropped: int = Field(default=0, ge=0, description="Frames dropped by keep-newest back-pressure.")
    rejected: int = Field(default=0, ge=0, description="Messages refused as bad input.")
    dictionary: list[str] = Field(default_factory=list, description="Names of the fingerprints held.")


class ErrorReport(Message):
    """A refused input (key ``fp/<rig>/errors``): which field, and what was expected."""

    schema_name: Literal["ErrorReport"] = "ErrorReport"
    frame_index: int | None = Field(default=None, ge=0)
    key: str = Field(description="Key expression the bad message arrived on.")
    field: str = Field(description="Field (dotted path) at fault.")
    problem: str = Field(description="What is wrong and what was expected.")
    header_excerpt: str = Field(default="", max_length=4096)
    node: str = ""
    timestamp: float = Field(default_factory=time.time, description="Wall-clock time of the report, s.")


#: schema name → model class, for every message that can travel on the wire.
MESSAGE_TYPES: dict[str, type[Message]] = {
    cls.model_fields["schema_name"].default: cls
    for cls in (RFFrame, GammaMap, ConfocalImage, Detections, Tracks, Status, ErrorReport)
}


def examples() -> dict[str, Message]:
    """One small, valid instance of every message type (keyed by schema name), for tests and docs."""
    from services.topics import keys

    n_u, n_theta, n_t = 4, 3, 16
    x = (np.arange(n_u) - (n_u - 1) / 2) * 3e-4
    probe = Probe(
        positions=np.stack([x, np.zeros(n_u), np.zeros(n_u)], axis=1),
        pitch=3e-4,
        centre_frequency=2.2e6,
        bandwidth=0.8e6,
    )
    sines = np.stack([np.linspace(-0.2, 0.2, n_theta), np.zeros(n_theta)], axis=1)
    rf = np.sin(np.arange(n_u * n_theta * n_t, dtype=np.float32)).reshape(n_u, n_theta, n_t)
    grid = Grid(x=np.linspace(-1e-3, 1e-3, 5), z=np.linspace(9e-3, 11e-3, 6))
    ramp = np.linspace(0, 1, 30, dtype=np.float32).reshape(grid.shape)
    det = Detection(
        fingerprint="sphere_10mm",
        position_m=(0.0, 0.0, 0.01),
        gamma_max=0.7,
        contrast_c_gamma=8.0,
        contrast_c=30.0,
        pfa=1e-6,
        precision_m=(1e-4, 2e-5),
    )
    track = Track(
        id=1,
        position_m=(0.0, 0.0, 0.01),
        velocity_m_s=(0.0, 0.0, 1e-3),
        covariance=((1e-8, 0.0, 0.0), (0.0, 1e-8, 0.0), (0.0, 0.0, 1e-8)),
        confidence=0.8,
        age=3,
    )
    msgs: list[Message] = [
        RFFrame(
            frame_index=1,
            timestamp=0.1,
            fs=20e6,
            t0=0.0,
            c0=1500.0,
            probe=probe,
            sines=sines,
            rf=rf,
            prf=5e3,
            truth={"position_m": [0.0, 0.0, 0.01]},
        ),
        GammaMap(frame_index=1, timestamp=0.1, fingerprint="sphere_10mm", grid=grid, gamma=ramp),
        ConfocalImage(frame_index=1, timestamp=0.1, grid=grid, image=ramp),
        Detections(frame_index=1, timestamp=0.1, detections=[det]),
        Tracks(frame_index=1, timestamp=0.1, tracks=[track]),
        Status(node="processor", timestamp=0.0, frames_processed=1, dictionary=["sphere_10mm"]),
        ErrorReport(frame_index=1, key=keys("demo").rf, field="rf", problem="contains NaN or inf", timestamp=0.0),
    ]
    return {m.schema_name: m for m in msgs}
