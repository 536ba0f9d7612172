"""Named parameter blocks: the one place that knows where each calibration parameter sits in theta.

Estimators address theta, its covariance and its SI scaling only through a `Layout` of `ParamBlock`s
(b_a, b_g, D, o, dip and any effect blocks). A block's `si_scale` says how its values convert:
- "field": proportional to the magnetometer's unit (internally the ellipsoid-fit scale, tesla in SI, the
  log's native unit in documents), e.g. D, o, mag/ampere;
- "angle": radians internally and in SI, degrees in documents (the dip);
- "none": SI throughout (m/s^2, rad/s, s, m, fractions).
"""

from __future__ import annotations

import builtins
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

from magcal_cli.streams import FloatArray

IntArray = npt.NDArray[np.int64]

SI_SCALES = ("field", "angle", "none")


@dataclass(frozen=True)
class ParamBlock:
    """A named run of theta entries: size, SI conversion kind, observability group and entry labels."""

    name: str
    size: int
    si_scale: str = "none"
    group: str = ""
    labels: tuple[str, ...] = ()
    #: the value's array shape, filled column-major from the entries; () means a vector (a scalar when size is 1)
    shape: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        if self.si_scale not in SI_SCALES:
            msg = f"parameter block {self.name!r}: si_scale {self.si_scale!r} is not one of {SI_SCALES}"
            raise ValueError(msg)
        if self.labels and len(self.labels) != self.size:
            msg = f"parameter block {self.name!r}: {len(self.labels)} labels for {self.size} entries"
            raise ValueError(msg)
        if self.shape and int(np.prod(self.shape)) != self.size:
            msg = f"parameter block {self.name!r}: shape {self.shape} does not hold {self.size} entries"
            raise ValueError(msg)

    def unflatten(self, values: FloatArray) -> FloatArray:
        """The block's entries (..., size) as its value: (..., *shape) column-major, (...) for a scalar block."""
        lead = values.shape[:-1]
        if self.shape:
            k = len(self.shape)
            axes = (*range(len(lead)), *range(len(lead) + k - 1, len(lead) - 1, -1))
            return values.reshape(lead + self.shape[::-1]).transpose(axes)
        return values.reshape(lead) if self.size == 1 else values

    def entry_names(self) -> list[str]:
        """'name.label' per entry ('name' alone for a scalar block)."""
        if self.size == 1 and not self.labels:
            return [self.name]
        labels = self.labels or tuple(str(i) for i in range(self.size))
        return [f"{self.name}.{lab}" for lab in labels]


XYZ = ("x", "y", "z")
#: vec(D) column-major: D[i][j] is entry i + 3 j
D_LABELS = tuple(f"{i}{j}" for j in range(3) for i in range(3))

ACCEL_BIAS = ParamBlock("accelerometer_bias", 3, "none", "accelerometer bias", XYZ)
GYRO_BIAS = ParamBlock("gyroscope_bias", 3, "none", "gyroscope bias", XYZ)
D_BLOCK = ParamBlock("D", 9, "field", "soft-iron/misalignment matrix D", D_LABELS, (3, 3))
O_BLOCK = ParamBlock("o", 3, "field", "hard-iron offset o", XYZ)
DIP = ParamBlock("dip", 1, "angle", "dip angle")


class Layout:
    """An ordered tuple of blocks; hands out slices, columns, names and SI factors by block name."""

    def __init__(self, blocks: Iterable[ParamBlock]) -> None:
        self.blocks: tuple[ParamBlock, ...] = tuple(blocks)
        self._at: dict[str, int] = {}
        self._size: dict[str, int] = {}
        #: `cols` by names: the solver's linearisations ask for the same columns thousands of times
        self._cols: dict[tuple[str, ...], IntArray] = {}
        at = 0
        for b in self.blocks:
            if b.name in self._at:
                msg = f"parameter block {b.name!r} appears twice in a layout"
                raise ValueError(msg)
            self._at[b.name] = at
            self._size[b.name] = b.size
            at += b.size
        self.size = at

    def __contains__(self, name: object) -> bool:
        return name in self._at

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Layout) and self.blocks == other.blocks

    def __hash__(self) -> int:
        return hash(self.blocks)

    def __repr__(self) -> str:
        return f"Layout({', '.join(f'{b.name}[{b.size}]' for b in self.blocks)})"

    @property
    def names(self) -> tuple[str, ...]:
        """Block names in order."""
        return tuple(b.name for b in self.blocks)

    def block(self, name: str) -> ParamBlock:
        """The block called `name`."""
        return self.blocks[self.names.index(name)]

    def slice(self, name: str) -> slice:
        """Where block `name` sits in theta."""
        try:
            at = self._at[name]
        except KeyError:
            msg = f"no parameter block {name!r} in {self!r}"
            raise KeyError(msg) from None
        return slice(at, at + self._size[name])

    def span(self, first: str, last: str) -> builtins.slice:
        """The contiguous run of theta from block `first` through block `last`."""
        start, stop = self.slice(first).start, self.slice(last).stop
        if stop <= start:
            msg = f"parameter block {first!r} comes after {last!r} in {self!r}"
            raise ValueError(msg)
        return slice(start, stop)

    def cols(self, *names: str) -> IntArray:
        """Theta columns of the named blocks, in the order given."""
        got = self._cols.get(names)
        if got is None:
            parts = [np.arange(self.slice(n).start, self.slice(n).stop) for n in names]
            got = np.concatenate(parts).astype(np.int64) if parts else np.zeros(0, np.int64)
            self._cols[names] = got
        return got.copy()

    def get(self, theta: FloatArray, name: str) -> FloatArray:
        """Block `name` of theta (a view)."""
        return theta[..., self.slice(name)]

    def value(self, theta: FloatArray, name: str) -> FloatArray:
        """Block `name` of theta (..., size) in its shape (`ParamBlock.unflatten`): D as (..., 3, 3), dip as (...)."""
        return self.block(name).unflatten(self.get(theta, name))

    def put(self, theta: FloatArray, name: str, value: npt.ArrayLike) -> None:
        """Write block `name` of theta in place."""
        theta[..., self.slice(name)] = value

    def carry(self, theta: FloatArray, source: Layout, values: FloatArray) -> None:
        """Write into theta, in place, every block this layout shares with `source` (whose theta is values)."""
        for name in self.names:
            if name in source:
                self.put(theta, name, source.get(values, name))

    def zeros(self) -> FloatArray:
        """An all-zero theta (every effect block at its base-model value)."""
        return np.zeros(self.size)

    def entry_names(self) -> list[str]:
        """One name per theta entry."""
        return [n for b in self.blocks for n in b.entry_names()]

    def factors(self, kind_factor: Mapping[str, float]) -> FloatArray:
        """Per-entry factor from a map si_scale -> factor ('none' is 1 unless given)."""
        table = {"none": 1.0, **kind_factor}
        return np.concatenate([np.full(b.size, table.get(b.si_scale, 1.0)) for b in self.blocks]) \
            if self.blocks else np.zeros(0)

    def si_factors(self, field_scale: float) -> FloatArray:
        """theta_si = theta_internal * si_factors: field blocks carry the magnetometer scale (tesla)."""
        return self.factors({"field": field_scale})

    def groups(self) -> dict[str, IntArray]:
        """Observability group label -> theta columns (blocks without a group are left out)."""
        out: dict[str, list[int]] = {}
        for b in self.blocks:
            if b.group:
                out.setdefault(b.group, []).extend(range(self.slice(b.name).start, self.slice(b.name).stop))
        return {k: np.array(v, np.int64) for k, v in out.items()}

    def sub(self, names: Sequence[str]) -> Layout:
        """The layout of just these blocks, in this order."""
        return Layout(self.block(n) for n in names)

    def extended(self, blocks: Iterable[ParamBlock]) -> Layout:
        """This layout with blocks appended."""
        return Layout((*self.blocks, *blocks))

    def to_order(self) -> list[list[Any]]:
        """[[name, size, si_scale], ...] for documents."""
        return [[b.name, b.size, b.si_scale] for b in self.blocks]


#: the base joint-MAP calibration: accelerometer bias, gyro bias, D (column-major), o, dip
BASE = Layout((ACCEL_BIAS, GYRO_BIAS, D_BLOCK, O_BLOCK, DIP))
#: one magnetometer's base parameters (what a calibration document's covariance holds)
MAG = BASE.sub(("D", "o", "dip"))


@dataclass(frozen=True, eq=False)
class Estimate:
    """Values and covariance addressed by block name (any units the owner states)."""

    layout: Layout
    value: FloatArray
    cov: FloatArray = field(default_factory=lambda: np.zeros((0, 0)))

    def __post_init__(self) -> None:
        value = np.array(self.value, dtype=np.float64).reshape(self.layout.size)
        cov = np.array(self.cov, dtype=np.float64)
        if cov.size == 0:
            cov = np.full((self.layout.size, self.layout.size), np.nan)
        cov = cov.reshape(self.layout.size, self.layout.size)
        value.flags.writeable = cov.flags.writeable = False
        object.__setattr__(self, "value", value)
        object.__setattr__(self, "cov", cov)

    def __getitem__(self, name: str) -> FloatArray:
        return self.value[self.layout.slice(name)]

    def std(self, name: str | None = None) -> FloatArray:
        """Marginal standard deviations of block `name` (of everything when None)."""
        sd = np.sqrt(np.clip(np.diag(self.cov), 0.0, None))
        return sd if name is None else sd[self.layout.slice(name)]

    def cov_of(self, *names: str) -> FloatArray:
        """The joint covariance of the named blocks."""
        c = self.layout.cols(*names)
        return self.cov[np.ix_(c, c)]

    def select(self, names: Sequence[str]) -> Estimate:
        """The named blocks only (marginal)."""
        c = self.layout.cols(*names)
        return Estimate(self.layout.sub(names), self.value[c], self.cov[np.ix_(c, c)])

    def scaled(self, factors: FloatArray) -> Estimate:
        """Values times factors (p,), covariance times their outer product (a unit change)."""
        return Estimate(self.layout, self.value * factors, self.cov * np.outer(factors, factors))
