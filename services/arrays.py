"""Array fields of the message models (``services.messages``) and their wire descriptors.

An array field is declared ``Annotated[np.ndarray, ArraySpec(...)]`` (:func:`array_field`): allowed
dtypes (the first is the default), ndim, fixed trailing dimensions, finiteness, minimum size. In
Python an array-like is accepted and cast only when the cast is safe; when decoding (the wire layer
passes the payload's buffers in the validation context) the field holds a buffer *name*, resolved to
the buffer, whose dtype must be one the field allows. In JSON Schema an array field is a string naming
a buffer, with ``x-array`` describing it. :class:`ArrayDescriptor` is one entry of a header's
``arrays`` list (name, dtype, shape, offset, nbytes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    GetCoreSchemaHandler,
    GetJsonSchemaHandler,
    ValidationInfo,
    model_validator,
)
from pydantic.json_schema import JsonSchemaValue
from pydantic_core import core_schema

__all__ = [
    "ALLOWED_DTYPES",
    "ARRAY_NAME_PATTERN",
    "ArrayDescriptor",
    "ArrayFieldError",
    "ArraySpec",
    "array_field",
]

ARRAY_NAME_PATTERN = r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z0-9_]+)*$"

#: dtypes a buffer may have on the wire (numpy ``dtype.str``, little-endian or single byte).
ALLOWED_DTYPES: tuple[str, ...] = (
    "|b1",
    "|u1",
    "|i1",
    "<u2",
    "<i2",
    "<u4",
    "<i4",
    "<u8",
    "<i8",
    "<f2",
    "<f4",
    "<f8",
    "<c8",
    "<c16",
)


class ArrayFieldError(ValueError):
    """A model-level check failed on a named field (the wire layer reports ``field``)."""

    def __init__(self, field: str, problem: str) -> None:
        self.field = field
        self.problem = problem
        super().__init__(f"{field}: {problem}")


def _dtype_names(dtypes: tuple[np.dtype, ...]) -> str:
    return " or ".join(d.name for d in dtypes)


@dataclass(frozen=True)
class ArraySpec:
    """Constraints of an array field: allowed dtypes (first one is the default), ndim, fixed
    trailing dimensions and whether every value must be finite."""

    dtypes: tuple[str, ...]
    ndim: int | None = None
    trailing: tuple[int, ...] = ()
    finite: bool = False
    min_size: int = 0

    def __post_init__(self) -> None:
        for d in self.dtypes:
            if np.dtype(d).str not in ALLOWED_DTYPES:
                raise ValueError(f"ArraySpec: dtype {d!r} cannot travel on the wire")

    @property
    def np_dtypes(self) -> tuple[np.dtype, ...]:
        return tuple(np.dtype(d).newbyteorder("<") for d in self.dtypes)

    def __get_pydantic_core_schema__(self, source: Any, handler: GetCoreSchemaHandler) -> core_schema.CoreSchema:
        return core_schema.with_info_plain_validator_function(
            self.validate,
            serialization=core_schema.plain_serializer_function_ser_schema(
                _serialize_array, info_arg=True, when_used="json"
            ),
        )

    def __get_pydantic_json_schema__(
        self, cs: core_schema.CoreSchema, handler: GetJsonSchemaHandler
    ) -> JsonSchemaValue:
        spec: dict[str, Any] = {"dtype": [d.str for d in self.np_dtypes]}
        if self.ndim is not None:
            spec["ndim"] = self.ndim
        if self.trailing:
            spec["trailing_shape"] = list(self.trailing)
        if self.finite:
            spec["finite"] = True
        return {
            "type": "string",
            "pattern": ARRAY_NAME_PATTERN,
            "description": "Name of the buffer (an entry of `arrays`) that holds this array.",
            "x-array": spec,
        }

    def validate(self, value: Any, info: ValidationInfo) -> np.ndarray:
        """Resolve a buffer reference (decoding) or accept an array-like (Python), then check it."""
        ctx = info.context if isinstance(info.context, dict) else None
        buffers = ctx.get("arrays") if ctx is not None else None
        allowed = self.np_dtypes
        if buffers is not None:
            if not isinstance(value, str):
                raise ValueError("expected the name of a buffer listed in 'arrays'")
            if value not in buffers:
                raise ValueError(f"buffer {value!r} is not described in 'arrays'")
            ctx["used"].add(value)  # type: ignore[index]
            arr = buffers[value]
            if arr.dtype not in allowed:
                raise ValueError(f"expected dtype {_dtype_names(allowed)}, got {arr.dtype.str}")
        else:
            if isinstance(value, str):
                raise ValueError("expected an array, got a buffer name outside wire decoding")
            arr = value if isinstance(value, np.ndarray) else np.asarray(value)
            if arr.dtype.byteorder == ">":
                arr = arr.astype(arr.dtype.newbyteorder("<"))
            if arr.dtype not in allowed:
                if arr.dtype.kind in "biufc" and np.can_cast(arr.dtype, allowed[0], "safe"):
                    arr = arr.astype(allowed[0])
                else:
                    raise ValueError(f"expected dtype {_dtype_names(allowed)}, got {arr.dtype} (cast it explicitly)")
        if self.ndim is not None and arr.ndim != self.ndim:
            raise ValueError(f"expected {self.ndim} dimensions, got shape {arr.shape}")
        if self.trailing and tuple(arr.shape[arr.ndim - len(self.trailing) :]) != self.trailing:
            want = ", ".join(["N"] * (arr.ndim - len(self.trailing)) + [str(t) for t in self.trailing])
            raise ValueError(f"expected shape ({want}), got {arr.shape}")
        if arr.size < self.min_size:
            raise ValueError(f"expected at least {self.min_size} element(s), got shape {arr.shape}")
        if self.finite and arr.dtype.kind in "fc" and arr.size and not _all_finite(arr):
            raise ValueError("contains NaN or inf; expected finite values")
        return arr


def _all_finite(arr: np.ndarray) -> bool:
    """True if no NaN/inf, without allocating an array-sized temporary (min/max propagate NaN)."""
    if arr.dtype.kind == "c":
        return _all_finite(arr.real) and _all_finite(arr.imag)
    return bool(np.isfinite(np.min(arr)) and np.isfinite(np.max(arr)))


def _serialize_array(arr: np.ndarray, info: Any) -> str:
    names = info.context.get("array_names") if isinstance(info.context, dict) else None
    if names is not None and id(arr) in names:
        return names[id(arr)]
    return f"<ndarray {arr.dtype} {tuple(arr.shape)}>"


def array_field(
    *dtypes: str, ndim: int | None = None, trailing: tuple[int, ...] = (), finite: bool = False, min_size: int = 0
) -> ArraySpec:
    return ArraySpec(tuple(dtypes), ndim, trailing, finite, min_size)


class ArrayDescriptor(BaseModel):
    """Where one array buffer lies in the payload. ``offset`` counts from the start of the data
    section (a multiple of 64); ``nbytes`` = prod(shape) × itemsize."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(pattern=ARRAY_NAME_PATTERN, max_length=256, description="Dotted field path.")
    dtype: str = Field(
        description="numpy dtype string, little-endian or single-byte.",
        json_schema_extra={"enum": list(ALLOWED_DTYPES)},
    )
    shape: list[Annotated[int, Field(ge=0)]] = Field(max_length=32)
    offset: int = Field(ge=0, multiple_of=64, description="Bytes from the start of the data section.")
    nbytes: int = Field(ge=0)

    @model_validator(mode="after")
    def _check(self) -> ArrayDescriptor:
        if self.dtype not in ALLOWED_DTYPES:
            try:
                dt = np.dtype(self.dtype)
            except TypeError:
                dt = None
            if dt is not None and dt.byteorder == ">":
                raise ArrayFieldError(
                    "dtype", f"{self.dtype!r} is big-endian; expected little-endian {dt.newbyteorder('<').str!r}"
                )
            raise ArrayFieldError("dtype", f"{self.dtype!r} is not one of {', '.join(ALLOWED_DTYPES)}")
        expected = math.prod(self.shape) * np.dtype(self.dtype).itemsize
        if self.nbytes != expected:
            raise ArrayFieldError(
                "nbytes", f"{self.nbytes} does not match shape {tuple(self.shape)} × {self.dtype} = {expected}"
            )
        return self
