"""Request and response bodies of the REST API (pydantic stays here, at the HTTP edge).

The scene's parameters are declared once, in ``engine/params.py``: each field below that
carries one takes its default, its description (help, unit, range, default) and its range or
choices (as JSON-schema keywords, shown at ``/docs``) from that declaration through
:func:`declared`. The values themselves are checked by the engine's value objects
(``GridSpec``, ``NoiseModel``, ``FusionParams``), so that the REST API, the command line and
the Python API refuse the same values with the same message (422, ``"rho: outlier
probability must be in (0, 1/2), got 0.7"``).
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field
from rangefuse.engine import FusionParams, GridSpec
from rangefuse.engine.params import PARAMS
from rangefuse.storage.catalog import ScanRow, SceneRow

from ..queue import JobRow

__all__ = [
    "Accepted",
    "Health",
    "JobOut",
    "JobRef",
    "NoiseIn",
    "NoiseOut",
    "Problem",
    "ReconstructionIn",
    "ScanOut",
    "SceneDetail",
    "SceneIn",
    "SceneOut",
    "StoredScan",
    "Upload",
    "declared",
    "problems",
]


def declared(name: str, *, response: bool = False, note: str = "") -> Any:
    """The pydantic ``Field`` of parameter ``name`` as declared in ``engine/params.py``.

    A request field gets the declared default (none when required); a response field
    (``response=True``) is always present and gets only the description and schema.
    ``note`` adds a sentence to the description.
    """
    param = PARAMS[name]
    extra = param.json_schema()
    description = param.describe() + (f"; {note}" if note else "")
    if response:
        return Field(description=description, json_schema_extra=extra)
    default = ... if param.required else param.default
    return Field(default=default, description=description, json_schema_extra=extra)


# --- requests ---------------------------------------------------------------------------------

_SENSOR_HELP = (
    "the scene's default sensor, as in sensor.json (docs/formats.md): uploads whose meta "
    "gives no sensor (and .npz scans that hold none) use it"
)


class NoiseIn(BaseModel):
    """The scene's default noise model (METHOD §1); a scan's ``meta.noise`` overrides it."""

    model_config = ConfigDict(extra="forbid")
    eps: float | None = declared("eps")
    eps_per_m: float = declared("eps_per_m")
    rho: float = declared("rho")
    falloff: float | None = declared("falloff")
    shape: str = declared("shape")


class SceneIn(BaseModel):
    """A new scene: its grid, its noise model and how scans are fused."""

    model_config = ConfigDict(extra="forbid")
    name: str = Field(min_length=1, max_length=200, description="a name for people")
    voxel_size: float = declared("voxel_size")
    tile_size: int = declared("tile_size")
    mode: str = declared("mode")
    bounds: list[float] | None = declared("bounds", note="closed mode needs one")
    noise: NoiseIn | None = Field(default=None, description="noise model (defaults as below)")
    filter: str = declared("filter")
    max_discontinuity: float | None = declared("max_discontinuity")
    no_return: str = declared("no_return")
    sensor: dict[str, Any] | None = Field(
        default=None,
        description=_SENSOR_HELP + "; without one, the first uploaded scan's sensor becomes it",
    )


class ReconstructionIn(BaseModel):
    """What to mesh: the scene's region of interest (or every tile), refined or not."""

    model_config = ConfigDict(extra="forbid")
    bounds: list[float] | None = Field(
        default=None,
        description="mesh only this box [x0, y0, z0, x1, y1, z1], world metres "
        "(default: the scene's region of interest, or every tile)",
        json_schema_extra=PARAMS["bounds"].json_schema(),
    )
    refine: bool = Field(
        default=True,
        description="re-evaluate the scans along each crossing cube edge (METHOD §3); "
        "false: linear interpolation of the log-odds (faster, less accurate)",
    )


# --- responses --------------------------------------------------------------------------------


class Problem(BaseModel):
    """Every refused request: what is wrong, naming the field or part."""

    detail: str


class Health(BaseModel):
    status: str = Field(description="ok, or why jobs cannot make progress")
    workers: int = Field(description="Dask workers that can run units of work now")


class NoiseOut(BaseModel):
    """The scene's noise model with every default filled in. Without a ``falloff`` of its
    own the fall-off is the noise half-width at each range, ``eps + eps_per_m * r``: that is
    ``eps`` when ``eps_per_m`` is 0, and no single number (null) otherwise."""

    eps: float = declared("eps", response=True)
    eps_per_m: float = declared("eps_per_m", response=True)
    rho: float = declared("rho", response=True)
    falloff: float | None = declared(
        "falloff", response=True, note="null: eps + eps_per_m * r, the half-width at range r"
    )
    shape: str = declared("shape", response=True)


class SceneOut(BaseModel):
    """A scene with every default filled in."""

    id: str
    name: str
    voxel_size: float = declared("voxel_size", response=True)
    tile_size: int = declared("tile_size", response=True)
    mode: str = declared("mode", response=True)
    bounds: list[float] | None = declared("bounds", response=True)
    noise: NoiseOut
    filter: str = declared("filter", response=True)
    max_discontinuity: float | None = declared("max_discontinuity", response=True)
    no_return: str = declared("no_return", response=True)
    sensor: dict[str, Any] | None = Field(description=_SENSOR_HELP + "; null: none yet")
    created_at: float = Field(description="seconds since the epoch")

    @classmethod
    def from_row(cls, row: SceneRow) -> SceneOut:
        grid = GridSpec.from_dict(row.grid)
        params = FusionParams.from_dict(row.params)
        n = params.noise
        return cls(
            id=row.id,
            name=row.name,
            voxel_size=grid.voxel_size,
            tile_size=grid.tile_size,
            mode=grid.mode,
            bounds=None if grid.bounds is None else list(grid.bounds),
            noise=NoiseOut(
                eps=n.eps,
                eps_per_m=n.eps_per_m,
                rho=n.rho,
                falloff=n.falloff if n.falloff is not None or n.eps_per_m else n.eps,
                shape=n.shape,
            ),
            filter=params.filter,
            max_discontinuity=params.max_discontinuity,
            no_return=params.no_return,
            sensor=row.sensor,
            created_at=row.created_at,
        )


class SceneDetail(SceneOut):
    """One scene, with the number of its scans and tiles."""

    scans: int
    tiles: int


class ScanOut(BaseModel):
    """A scan: ``stored`` (archived, acknowledged), ``fused`` or ``removing``."""

    id: str
    name: str | None
    state: str
    seq: int = Field(description="order of arrival in the scene, from 1")
    checksum: str
    created_at: float
    far_ranges: int | None = Field(
        description="finite ranges beyond the sensor's max_range, treated as invalid (not "
        "surfaces): counted when the scan was decoded (null: stored before they were recorded)"
    )

    @classmethod
    def from_row(cls, row: ScanRow) -> ScanOut:
        return cls(id=row.id, name=row.name, state=row.state, seq=row.seq,
                   checksum=row.checksum, created_at=row.created_at,
                   far_ranges=row.far_ranges)  # fmt: skip


class StoredScan(BaseModel):
    id: str
    name: str | None
    state: str
    far_ranges: int = Field(
        default=0,
        description="finite ranges beyond the sensor's max_range, treated as invalid (not "
        "surfaces): counted when the scan was decoded",
    )


class JobRef(BaseModel):
    id: str


class Accepted(BaseModel):
    """202: the job that does the work; follow it at ``GET /v1/jobs/{id}``."""

    job: JobRef


class Upload(BaseModel):
    """202: the scan is on disk (archived with fsync) and queued for fusion by ``job``."""

    scan: StoredScan
    job: JobRef


class JobOut(BaseModel):
    """A job (``message``, ``error``, ``finished_at`` and ``result`` only once there is
    one)."""

    id: str
    kind: str = Field(description="integrate, remove, reconstruct or delete (a scene)")
    scene_id: str | None
    state: str = Field(
        description="queued, running, cancelling (a running job asked to stop), done, failed "
        "or cancelled"
    )
    progress: float = Field(description="0 to 1")
    message: str | None = Field(
        default=None,
        description="what a running job waits on, for people, e.g. 'compiling kernels, first "
        "run only (...)' while a worker compiles the kernels its units need (docs/service.md)",
    )
    created_at: float
    error: str | None = None
    finished_at: float | None = None
    result: dict[str, Any] | None = None

    @classmethod
    def from_row(cls, job: JobRow) -> JobOut:
        """Only the fields the job has are set (routes exclude the unset ones)."""
        return cls(**job.to_dict())


_PROBLEMS = {
    400: "a malformed request body: an upload's part, or JSON that cannot be parsed (the "
    "message names the part and the problem)",
    401: "no valid bearer token",
    403: "a token of the wrong role (an admin token on a tenant's route)",
    404: "no such id (another tenant's ids look the same)",
    409: "the store refused (a conflict), the scene is being deleted, no reconstruction yet, "
    "or a job already finished",
    503: "no worker can run jobs",
    413: "a request body over RANGEFUSE_MAX_UPLOAD_MB",
    422: "an invalid value (the message names the field and the problem)",
    507: "the store's disk is full (nothing was stored; retry once space is freed)",
}


def problems(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` for error status codes: each a :class:`Problem`."""
    return {code: {"model": Problem, "description": _PROBLEMS[code]} for code in codes}
