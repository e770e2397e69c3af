"""The scene's parameters, each declared once: name, unit, default, valid range, help.

Every fusion and grid parameter is one :class:`Param` in :data:`PARAMS`. The value objects
validate their fields with it (:class:`~engine.grid.GridSpec`, :class:`~engine.certainty.
NoiseModel`, :class:`~engine.scans.FusionParams`), the command line builds the options of
``rangefuse fuse`` from it and the REST API its scene models (``service/cli.py``,
``service/api/models.py``): a name, default, range or help text is written here and nowhere
else. Like nvblox's ``*_params.h``, each declaration is a plain record (name, default,
help) beside the code, not a configuration file; unlike kiss-icp's config it also carries
the valid range, so that the three front ends refuse the same values with the same words.

One name per concept, everywhere (dataclass field, dict key, REST field; ``--eps-per-m`` on
the command line). Paper symbols (METHOD.md) are in :attr:`Param.symbol`. Before the names
were unified, stored scenes and archived scans recorded some parameters under names with a
unit suffix (``voxel_size_m``, ``eps_m`` ...); :func:`current_names` reads such a record
under today's names, so stores written then still open.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from fractions import Fraction
from typing import Any

from .defaults import EPS_PER_VOXEL, RHO, TILE_SIZE_VOX
from .errors import InvalidInputError
from .filters import FILTERS

__all__ = [
    "GROUPS",
    "LEGACY_NAMES",
    "PARAMS",
    "Param",
    "current_names",
    "default_eps",
    "params_of",
]

#: Which value object holds a parameter: grid -> GridSpec, noise -> NoiseModel (the REST
#: API's nested ``noise`` object), fusion -> FusionParams.
GROUPS = ("grid", "noise", "fusion")
#: Kinds of value: a real number, an integer, one of ``choices``, six numbers (a box).
KINDS = ("float", "int", "choice", "bounds")
_UNIT_WORDS = {"m": "metres", "voxels": "voxels", "": ""}


@dataclass(frozen=True)
class Param:
    """The declaration of one parameter.

    Parameters
    ----------
    name : str
        The one name: dataclass field, dict key, REST field; ``--name-with-dashes`` on the
        command line.
    group : {"grid", "noise", "fusion"}
        The value object that holds it.
    kind : {"float", "int", "choice", "bounds"}
        What a value is.
    help : str
        One line: what it means (without unit, range or default, which are added).
    unit : {"m", "voxels", ""}
        ``""``: a pure number.
    default : object
        The value when none is given; ``None`` with ``default_text`` when the default is
        derived (``eps``: 2 voxels) or means "off" (``max_discontinuity``).
    default_text : str
        The default in words when it is not a plain value.
    required : bool
        The front ends need a value (``voxel_size``).
    nullable : bool
        ``None`` is a valid value of the dataclass field (off, derived, no box).
    choices : tuple of str
        The valid values of a ``choice``.
    low, high : float or None
        The valid range of a number; ``low_inclusive`` / ``high_inclusive`` close it.
    what : str
        A noun put before the range problem ("outlier probability must be in ...").
    too_high : str
        The problem above ``high`` (``{}`` is the value) when it is not "must be in".
    symbol : str
        The symbol of METHOD.md, where there is one.
    metavar : str
        The placeholder of the command line (``M`` metres, ``N`` a count, ``P``, ``F``).
    """

    name: str
    group: str
    kind: str
    help: str
    unit: str = ""
    default: Any = None
    default_text: str = ""
    required: bool = False
    nullable: bool = False
    choices: tuple[str, ...] = ()
    low: float | None = None
    low_inclusive: bool = False
    high: float | None = None
    high_inclusive: bool = False
    what: str = ""
    too_high: str = ""
    symbol: str = ""
    metavar: str = ""

    def __post_init__(self) -> None:
        if self.group not in GROUPS or self.kind not in KINDS or self.unit not in _UNIT_WORDS:
            raise ValueError(f"{self.name}: bad declaration")
        if (self.kind == "choice") != bool(self.choices):
            raise ValueError(f"{self.name}: choices go with kind 'choice'")

    # --- what the front ends show -------------------------------------------------------------
    @property
    def flag(self) -> str:
        """The command-line option: ``--eps-per-m``."""
        return "--" + self.name.replace("_", "-")

    @property
    def default_words(self) -> str:
        """``required``, ``default 0.05``, ``default 2 voxels``."""
        if self.required:
            return "required"
        if self.default_text:
            return f"default {self.default_text}"
        return f"default {_number(self.default) if self.kind != 'choice' else self.default}"

    def range_text(self, var: str | None = None) -> str:
        """The valid range as an inequality in ``var`` (default: the name): ``0 < rho < 1/2``."""
        var = var or self.name
        if self.kind == "choice":
            return f"one of {', '.join(self.choices)}"
        if self.low is None and self.high is None:
            return ""
        if self.high is None:
            return f"{var} {'>=' if self.low_inclusive else '>'} {_number(self.low)}"
        if self.low is None:
            return f"{var} {'<=' if self.high_inclusive else '<'} {_number(self.high)}"
        return (
            f"{_number(self.low)} {'<=' if self.low_inclusive else '<'} {var} "
            f"{'<=' if self.high_inclusive else '<'} {_number(self.high)}"
        )

    def describe(self, var: str | None = None) -> str:
        """Help, METHOD symbol, unit, range and default in one line (``--help``, OpenAPI)."""
        text = self.help
        if self.symbol:
            text += f" (METHOD: {self.symbol})"
        facts = [
            w for w in (_UNIT_WORDS[self.unit], "" if self.choices else self.range_text(var)) if w
        ]
        if facts:
            text += "; " + ", ".join(facts)
        return f"{text} ({self.default_words})"

    def json_schema(self) -> dict[str, Any]:
        """The range or choices as JSON-schema keywords (for the REST models)."""
        out: dict[str, Any] = {}
        if self.kind in ("float", "int"):
            if self.low is not None:
                out["minimum" if self.low_inclusive else "exclusiveMinimum"] = self.low
            if self.high is not None:
                out["maximum" if self.high_inclusive else "exclusiveMaximum"] = self.high
        elif self.kind == "choice":
            out["enum"] = list(self.choices)
        elif self.kind == "bounds":
            out["minItems"] = out["maxItems"] = 6
        return out

    # --- validation ---------------------------------------------------------------------------
    def validate(self, value: Any, error: type[InvalidInputError] = InvalidInputError) -> Any:
        """``value`` converted to the declared kind (float, int, str, tuple of six floats).

        Raises ``error(name, problem)`` when it is not a valid value; ``problem`` is the one
        text all front ends show.
        """
        problem, out = self._check(value)
        if problem:
            raise error(self.name, problem)
        return out

    def _check(self, value: Any) -> tuple[str, Any]:
        if value is None and self.nullable:
            return "", None
        if self.kind == "choice":
            if value not in self.choices:
                return f"must be one of {', '.join(self.choices)}, got {value!r}", value
            return "", value
        if self.kind == "bounds":
            return _check_bounds(value)
        if self.kind == "int":
            if isinstance(value, bool) or not isinstance(value, numbers.Integral):
                return f"must be an integer, got {value!r}", value
            number: float = int(value)
        else:
            if isinstance(value, bool):
                return f"must be a number, got {value!r}", value
            try:
                number = float(value)
            except (TypeError, ValueError):
                return f"must be a number, got {value!r}", value
            if not math.isfinite(number):
                return f"must be finite, got {value!r}", value
        if self._inside(number):
            return "", number
        return self._range_problem(number), number

    def _inside(self, x: float) -> bool:
        if self.low is not None and (x < self.low or (x == self.low and not self.low_inclusive)):
            return False
        return self.high is None or x < self.high or (x == self.high and self.high_inclusive)

    def _range_problem(self, x: float) -> str:
        if self.too_high and self.high is not None and x >= self.high:
            return self.too_high.format(x)
        if self.kind == "int":
            between = f"{_number(self.low)} and {_number(self.high)} {self.unit}"
            return f"must be between {between}, got {x}"
        if self.low == 0 and not self.low_inclusive and (self.high is None or self.too_high):
            unit = f" of {_UNIT_WORDS[self.unit]}" if self.unit else ""
            return f"must be a positive number{unit}, got {x}"
        lo = "[" if self.low_inclusive else "("
        hi = "]" if self.high_inclusive else ")"
        interval = f"{lo}{_number(self.low)}, {_number(self.high)}{hi}"
        return f"{self.what + ' ' if self.what else ''}must be in {interval}, got {x}"


def _number(x: Any) -> str:
    """``0.5`` as ``1/2``, ``4.0`` as ``4``, ``0.05`` as ``0.05``."""
    if x is None:
        return "none"
    x = float(x)
    if x.is_integer():
        return str(int(x))
    fraction = Fraction(x).limit_denominator(8)
    if float(fraction) == x:
        return f"{fraction.numerator}/{fraction.denominator}"
    return f"{x:g}"


def _check_bounds(value: Any) -> tuple[str, Any]:
    try:
        values = tuple(float(x) for x in value)
    except (TypeError, ValueError):
        return f"must be six numbers, got {value!r}", value
    if len(values) != 6:
        return f"must be six numbers [x0, y0, z0, x1, y1, z1], got {len(values)}", value
    if not all(math.isfinite(x) for x in values):
        return f"must be six finite numbers, got {list(values)}", value
    return "", values


PARAMS: dict[str, Param] = {
    p.name: p
    for p in (
        # grid: GridSpec
        Param(
            "voxel_size", "grid", "float", "voxel edge", unit="m", required=True,
            low=0.0, high=100.0, high_inclusive=True,
            too_high="{} m is not a sensible voxel size", symbol="h", metavar="M",
        ),
        Param(
            "tile_size", "grid", "int", "voxels per tile edge", unit="voxels",
            default=TILE_SIZE_VOX, low=4, low_inclusive=True, high=128, high_inclusive=True,
            metavar="N",
        ),
        Param(
            "mode", "grid", "choice",
            "mapping: tiles near observed surfaces, open meshes; closed: every tile of the "
            "region of interest that a line of sight crosses, closed meshes",
            default="mapping", choices=("mapping", "closed"),
        ),
        Param(
            "bounds", "grid", "bounds",
            "region of interest [x0, y0, z0, x1, y1, z1] in world coordinates",
            unit="m", nullable=True, default_text="none",
        ),
        # noise: NoiseModel (METHOD §1)
        Param(
            "eps", "noise", "float", "noise half-width at zero range", unit="m",
            default_text=f"{EPS_PER_VOXEL:g} voxels", low=0.0, symbol="eps0", metavar="M",
        ),
        Param(
            "eps_per_m", "noise", "float",
            "growth of the noise half-width per metre of range: eps = eps0 + eps1 * range",
            default=0.0, low=0.0, low_inclusive=True, high=1.0, symbol="eps1", metavar="F",
        ),
        Param(
            "rho", "noise", "float", "outlier probability", default=RHO, low=0.0, high=0.5,
            what="outlier probability", symbol="rho", metavar="P",
        ),
        Param(
            "falloff", "noise", "float",
            "distance behind the noise band over which the certainty returns to 1/2",
            unit="m", nullable=True, default_text="eps", low=0.0, metavar="M",
        ),
        Param(
            "shape", "noise", "choice",
            "certainty ramp: linear (the paper's) or erf (a Gaussian range error)",
            default="linear", choices=("linear", "erf"),
        ),
        # fusion: FusionParams (METHOD §4 step 2)
        Param(
            "filter", "fusion", "choice", "range-map filter: 5x5 mean or 3x3 median",
            default="none", choices=FILTERS,
        ),
        Param(
            "max_discontinuity", "fusion", "float",
            "ignore points whose four neighbouring ranges spread by more", unit="m",
            nullable=True, default_text="off", low=0.0, metavar="M",
        ),
        Param(
            "no_return", "fusion", "choice",
            "no-return pixels carve free space up to the sensor's max_range (free) or are "
            "ignored (invalid)",
            default="free", choices=("free", "invalid"),
        ),
    )
}  # fmt: skip


def params_of(group: str) -> tuple[Param, ...]:
    """The declarations of one group, in declaration order."""
    if group not in GROUPS:
        raise ValueError(f"unknown parameter group {group!r}")
    return tuple(p for p in PARAMS.values() if p.group == group)


def default_eps(voxel_size: float) -> float:
    """The noise half-width when none is given: ``EPS_PER_VOXEL`` voxels."""
    return EPS_PER_VOXEL * float(voxel_size)


#: Names that stored records used before, and the name each goes by now.
LEGACY_NAMES = {
    "voxel_size_m": "voxel_size",
    "tile_size_vox": "tile_size",
    "bounds_m": "bounds",
    "eps_m": "eps",
    "falloff_m": "falloff",
    "max_discontinuity_m": "max_discontinuity",
}


def current_names(data: dict[str, Any]) -> dict[str, Any]:
    """``data`` with every legacy key renamed (a key given under both names keeps today's)."""
    out = {LEGACY_NAMES.get(k, k): v for k, v in data.items() if k in LEGACY_NAMES}
    out.update({k: v for k, v in data.items() if k not in LEGACY_NAMES})
    return out
