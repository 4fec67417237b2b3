"""The scene file format as pydantic v2 models: one model per table of a scene file.

:class:`SceneSpec` is the whole file; its fields are the tables (:class:`MeshSpec`,
:class:`MaterialSpec`, :class:`DirichletSpec`, ...). Validation refuses unknown keys, wrong
types and impossible values; :func:`validate` turns pydantic's ``ValidationError`` into a
:class:`~jaxelastic.scene.errors.SceneError` that names the key as written in the file
(``[material].nu``), the bad value and the valid choices or range. :func:`json_schema` is
the JSON Schema of a scene file (``jaxelastic schema``), for editors with TOML schema
support (taplo / Even Better TOML). Checks that need the mesh's dimension run here when a
generator fixes it, else once a mesh file is read (:meth:`SceneSpec.dim_problem`).

Validation context (``model_validate(raw, context={"base_dir": ...})``): ``base_dir`` is the
directory that relative mesh paths and ``"module:function"`` imports resolve against.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Mapping
from typing import TYPE_CHECKING, Annotated, Any, ClassVar, Literal, Union

from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Discriminator,
    Field,
    PlainValidator,
    Strict,
    Tag,
    ValidationError,
    ValidationInfo,
    WithJsonSchema,
    field_validator,
    model_validator,
)

from ..dynamics import H_MIN
from ..materials import (
    BUILTIN,
    DIRECTION_KEYS,
    FAMILIES,
    FAMILY_KEYS,
    FAMILY_POSITIVE_KEYS,
    MODEL_NAMES,
    MaterialParameterError,
    check_family,
)
from ..mesh import FORMULATIONS
from .callables import CallableSpecError, import_callable, n_positional
from .errors import SceneError, fail, from_validation_error, type_name
from .where import WhereError, check_where

__all__ = [
    "AXES",
    "GENERATOR_DIM",
    "axis_index",
    "SceneSpec",
    "MeshSpec",
    "MaterialSpec",
    "FibreCellData",
    "FibreRegion",
    "FibreRule",
    "Selector",
    "PlaneSelector",
    "BoxSelector",
    "Rotation",
    "RotateDisplacement",
    "DirichletSpec",
    "TractionSpec",
    "PointLoadSpec",
    "GravitySpec",
    "PressureSpec",
    "CavitySpec",
    "ObstacleSpec",
    "ContactSpec",
    "SolverSpec",
    "StaticIntegrator",
    "DynamicIntegrator",
    "OutputSpec",
    "FitTarget",
    "FitInitial",
    "FitObservation",
    "FIT_KINDS",
    "fit_parameters",
    "FitCase",
    "FitSpec",
    "validate",
    "json_schema",
]

GENERATOR_DIM = {"box": 3, "rectangle": 2, "cook": 2}
"""Spatial dimension of each mesh generator."""
AXES = {"x": 0, "y": 1, "z": 2}
"""Axis names and their indices."""
CALLABLE_PATTERN = r"^[A-Za-z_][\w.]*:[A-Za-z_][\w.]*$"


def axis_index(a) -> int:
    """``0/1/2`` or ``"x"/"y"/"z"`` → the axis index."""
    return AXES[a] if isinstance(a, str) else int(a)


def _base_dir(info: ValidationInfo) -> str:
    ctx = info.context or {}
    return os.path.abspath(ctx.get("base_dir") or os.getcwd())


# ----------------------------------------------------------------------------------------
# value types
# ----------------------------------------------------------------------------------------

Number = Annotated[float, Strict(), Field(allow_inf_nan=False)]
Positive = Annotated[Number, Field(gt=0)]
NonNegative = Annotated[Number, Field(ge=0)]
Integer = Annotated[int, Strict()]
Bool = Annotated[bool, Strict()]
Str = Annotated[str, Strict()]
Vector = Annotated[tuple[Number, ...], Field(min_length=1)]
"""One entry per mesh dimension."""


def _kind(v) -> str:
    if isinstance(v, str):
        return "str"
    if isinstance(v, (Mapping, BaseModel)):
        return "table"
    if isinstance(v, (list, tuple)):
        return "array"
    return "scalar"


def either(default: str, **alternatives):
    """A union chosen by the TOML type of the value (``str``, ``table``, ``array``,
    ``scalar``; other types go to ``default``), so that errors name one alternative."""

    def pick(v) -> str:
        k = _kind(v)
        return f"~{k if k in alternatives else default}"

    members = tuple(Annotated[t, Tag(f"~{k}")] for k, t in alternatives.items())
    return Annotated[Union[members], Discriminator(pick)]  # noqa: UP007


def _axis(v):
    if (isinstance(v, str) and v in AXES) or (type(v) is int and 0 <= v <= 2):
        return v
    raise fail(f"{{at}} must be 0, 1, 2 or 'x', 'y', 'z', got {v!r}")


Axis = Annotated[
    Union[int, str],  # noqa: UP007
    PlainValidator(_axis),
    WithJsonSchema(
        {"anyOf": [{"type": "integer", "minimum": 0, "maximum": 2}, {"enum": ["x", "y", "z"]}]}
    ),
]
"""An axis: ``0/1/2`` or ``"x"/"y"/"z"``."""


def _importable(v: str, info: ValidationInfo) -> str:
    try:
        import_callable(v, _base_dir(info))
    except CallableSpecError as e:
        raise fail(f"{{at}}: {e}") from None
    return v


CallableName = Annotated[
    str,
    Strict(),
    AfterValidator(_importable),
    WithJsonSchema({"type": "string", "pattern": CALLABLE_PATTERN}),
]
"""``"module:function"``, imported with the scene file's directory first on ``sys.path``."""


def _where_ok(v: str) -> str:
    try:
        check_where(v)
    except WhereError as e:
        raise fail(f"{{at}}: {e} in {v!r}") from None
    return v


WhereExpr = Annotated[str, Strict(), AfterValidator(_where_ok)]
"""A boolean expression of the rest positions (see :mod:`jaxelastic.scene.where`)."""


def _array_of_tables(v):
    if isinstance(v, Mapping):
        raise fail("{at} must be an array of tables: write [{at}]")
    if not isinstance(v, (list, tuple)):
        raise fail(f"{{at}} must be an array of tables, got {type_name(v)}")
    return v


# ----------------------------------------------------------------------------------------
# the base table
# ----------------------------------------------------------------------------------------


class Table(BaseModel):
    """A table of a scene file: unknown keys are refused, the result is read-only."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    _unknown_suffix: ClassVar[str] = ""

    @model_validator(mode="before")
    @classmethod
    def _known_keys(cls, data):
        if isinstance(data, BaseModel):
            return data
        if not isinstance(data, Mapping):
            raise fail(f"{{at}} must be a table, got {type_name(data)} {data!r}")
        valid = [f.alias or k for k, f in cls.model_fields.items()]  # [contact] self
        for k in data:
            if k not in valid:
                raise fail(cls._unknown_key(k, valid))
        return cls._prepare(dict(data))

    @classmethod
    def _unknown_key(cls, key: str, valid: list) -> str:
        return f"unknown key {{at}}.{key}{cls._unknown_suffix} (valid: {', '.join(valid)})"

    @classmethod
    def _prepare(cls, data: dict) -> dict:
        """Cross-key checks and defaults on the raw table (before the fields are validated)."""
        return data


# ----------------------------------------------------------------------------------------
# [mesh]
# ----------------------------------------------------------------------------------------


_Count = Annotated[Integer, Field(ge=1)]
# (each either(...) union below is spelled out as its plain union for the type checker,
# which cannot evaluate the call; pydantic validates with the discriminated one)
if TYPE_CHECKING:
    CellCounts = _Count | tuple[_Count, ...]
else:
    CellCounts = either("scalar", scalar=_Count, array=tuple[_Count, ...])


class MeshSpec(Table):
    """The mesh: a generator (``box``, ``rectangle``, ``cook``) or a mesh file."""

    generator: Literal["box", "rectangle", "cook"] | None = Field(
        default=None,
        description='"box" (3D tets), "rectangle" (2D triangles) or "cook" (Cook\'s '
        "membrane, 2D); exactly one of generator and file",
    )
    file: Str | None = Field(
        default=None,
        description="any meshio-readable mesh file (Gmsh .msh, .vtu, .xdmf, ...), relative "
        "to the scene file; its named groups can be selected with { group = ... }",
    )
    n: CellCounts | None = Field(
        default=None,
        description='cells per axis, one per dimension (generator "cook": one integer, default 16)',
    )
    size: tuple[Positive, ...] | None = Field(
        default=None, description="box/rectangle extent per axis [m] (default: all 1)"
    )
    origin: Vector | None = Field(
        default=None,
        description="box/rectangle corner with the smallest coordinates [m] (default 0)",
    )
    order: Literal[1, 2] | None = Field(
        default=None,
        description="1 (P1, default for generators) or 2 (P2: tri6/tet10); a file keeps its "
        "own order unless given (order = 2 lifts a P1 file)",
    )
    formulation: Literal[FORMULATIONS] = Field(  # type: ignore[valid-type]
        default="standard",
        description='"standard", "fbar" (finite strain) or "bbar" (small strain, for '
        '"linear"): locking-free for nu -> 0.5; with order = 1 this is the composite '
        "element (tri3x4/tet4x8 on the P2 node set)",
    )

    @classmethod
    def _prepare(cls, t: dict) -> dict:
        if ("generator" in t) == ("file" in t):
            raise fail("{at} needs exactly one of generator = ... or file = ...")
        if "file" in t:
            for k in ("n", "size", "origin"):
                if k in t:
                    raise fail(
                        f"{{at}}.{k} is only valid with a generator (a file has its geometry)"
                    )
            return t
        gen = t["generator"]
        if gen == "cook":
            for k in ("size", "origin"):
                if k in t:
                    raise fail(f"{{at}}.{k} is not valid for generator 'cook' (fixed geometry)")
            n = t.get("n", 16)
            t["n"] = n[0] if isinstance(n, (list, tuple)) and len(n) == 1 else n
        elif gen in GENERATOR_DIM:
            if "n" not in t:
                raise fail(f"{{at}}.n is required for generator {gen!r}")
            dim = GENERATOR_DIM[gen]
            t.setdefault("size", [1.0] * dim)
            t.setdefault("origin", [0.0] * dim)
        t.setdefault("order", 1)
        return t

    @field_validator("file")
    @classmethod
    def _file_exists(cls, v, info: ValidationInfo):
        if v is None:
            return v
        path = os.path.normpath(os.path.join(_base_dir(info), os.path.expanduser(v)))
        if os.path.isdir(path):
            raise fail(f"{{at}}: {path!r} is a directory, not a mesh file")
        if not os.path.isfile(path):
            raise fail(f"{{at}}: no such mesh file {path!r}")
        return path

    @model_validator(mode="after")
    def _n_matches(self):
        gen = self.generator
        if gen == "cook" and not isinstance(self.n, int):
            raise fail(f"{{at}}.n must be an integer for 'cook', got {self.n!r}")
        if gen in ("box", "rectangle"):
            dim = GENERATOR_DIM[gen]
            if not isinstance(self.n, tuple) or len(self.n) != dim:
                n = list(self.n) if isinstance(self.n, tuple) else self.n
                raise fail(f"{{at}}.n must be an array of {dim} integers for {gen!r}, got {n!r}")
        return self


# ----------------------------------------------------------------------------------------
# [material]
# ----------------------------------------------------------------------------------------


_MODEL_NAMES = list(MODEL_NAMES)


def _material_model(v: str, info: ValidationInfo) -> str:
    if ":" in v:
        return _importable(v, info)
    if v not in BUILTIN and v not in FAMILIES:
        raise fail(
            f"{{at}}: unknown material {v!r} (built-in: {', '.join(_MODEL_NAMES)}; or "
            "'module:function' for your own psi(F, params))"
        )
    return v


MaterialModel = Annotated[
    str,
    Strict(),
    AfterValidator(_material_model),
    WithJsonSchema(
        {"anyOf": [{"enum": _MODEL_NAMES}, {"type": "string", "pattern": CALLABLE_PATTERN}]}
    ),
]


class FibreCellData(Table):
    """HGO fibre directions per cell, read from a cell-data array of ``[mesh].file``."""

    cell_data: Str = Field(
        description="name of a cell-data array of [mesh].file with shape (n_cells, 3) (2D: "
        "also (n_cells, 2)); every row nonzero (rows are normalised)"
    )


class FibreRegion(Table):
    """One HGO fibre region: the cells whose centroid satisfies ``where`` get ``direction``
    (the first matching region wins); the last region, without ``where``, is the default."""

    where: WhereExpr | None = Field(
        default=None,
        description='a boolean expression of the cell centroids (X, x, y, z), e.g. "x < 0.5"; '
        "required except in the last region (the default for the remaining cells)",
    )
    direction: Vector = Field(
        description="the fibre direction (reference) of these cells: 2 or 3 numbers, nonzero"
    )

    @model_validator(mode="after")
    def _nonzero(self):
        d = self.direction
        if len(d) not in (2, 3) or not any(d):
            raise fail(
                f"{{at}}.direction must be a nonzero vector of 2 or 3 numbers, got {list(d)}"
            )
        return self


def _default_last(v: tuple) -> tuple:
    for i, r in enumerate(v[:-1]):
        if r.where is None:
            raise fail(
                f"{{at}}[{i}] needs where = ... (only the last region, the default, has none)"
            )
    if v[-1].where is not None:
        raise fail(
            "{at}: the last region must be the default { direction = [..] } without where "
            "(the cells matching no region get it)"
        )
    return v


class FibreRule(Table):
    """Directions of the helix rule of a thick ellipsoidal ventricle (3D meshes), at the
    cell centroids or the quadrature points (:func:`jaxelastic.materials.helix_basis`)."""

    rule: Literal["helix", "transmural"] = Field(
        description='"helix": the fibre sin(a) e_u + cos(a) e_v with the helix angle a linear '
        'through the wall from endo to epi; "transmural": the outward normal of the '
        "ellipsoid through the cell (the rule's sheet direction, for s0)"
    )
    endo: Number = Field(
        default=90.0, description='helix angle on the endocardium [degrees] ("helix" only)'
    )
    epi: Number = Field(
        default=-90.0, description='helix angle on the epicardium [degrees] ("helix" only)'
    )
    endo_radii: tuple[Positive, Positive] = Field(
        default=(7.0, 17.0),
        description="(short, long) radii of the endocardium, in the mesh's length unit (the "
        "defaults: the ventricle of Land et al. 2015 in mm); the ellipsoids are centred at "
        "the origin with their long axis along z",
    )
    epi_radii: tuple[Positive, Positive] = Field(
        default=(10.0, 20.0), description="(short, long) radii of the epicardium"
    )
    at: Literal["cells", "quadrature"] = Field(
        default="cells",
        description='where the rule is sampled: "cells" (one direction per cell, at the '
        'centroid) or "quadrature" (one per quadrature point: resolves the helix through a '
        "wall only a few cells thick; the same cost per Newton step, n_q x the memory of "
        "the directions)",
    )

    @classmethod
    def _prepare(cls, t: dict) -> dict:
        if t.get("rule") == "transmural":
            for k in ("endo", "epi"):
                if k in t:
                    raise fail(f'{{at}}.{k} is a helix angle: only for rule = "helix"')
        return t

    @model_validator(mode="after")
    def _radii(self):
        (a0, b0), (a1, b1) = self.endo_radii, self.epi_radii
        if not (a0 < a1 and b0 < b1):
            raise fail(
                f"{{at}}: need endo_radii < epi_radii in both radii, got "
                f"{list(self.endo_radii)} and {list(self.epi_radii)}"
            )
        return self


FibreRegions = Annotated[
    tuple[FibreRegion, ...], Field(min_length=1), AfterValidator(_default_last)
]


def _fibre_kind(v) -> str:
    if isinstance(v, FibreRule) or (isinstance(v, Mapping) and "rule" in v):
        return "~rule"
    if isinstance(v, (Mapping, BaseModel)):
        return "~table"
    if isinstance(v, (list, tuple)) and v and all(isinstance(e, (Mapping, BaseModel)) for e in v):
        return "~regions"
    return "~array"


if TYPE_CHECKING:
    FibreDirection = Vector | FibreCellData | FibreRule | FibreRegions
else:
    FibreDirection = Annotated[
        Union[  # noqa: UP007
            Annotated[Vector, Tag("~array")],
            Annotated[FibreCellData, Tag("~table")],
            Annotated[FibreRule, Tag("~rule")],
            Annotated[FibreRegions, Tag("~regions")],
        ],
        Discriminator(_fibre_kind),
    ]
"""An HGO fibre direction: one vector for all cells, ``{ cell_data = "name" }``, a rule
(``{ rule = "helix", endo = 90, epi = -90 }``, :class:`FibreRule`), or an array of
:class:`FibreRegion` (``{ where = ..., direction = [..] }``, the default last)."""


class MaterialSpec(Table):
    """The material: a strain-energy density and its elastic parameters."""

    model: MaterialModel = Field(
        description="a built-in psi (" + ", ".join(_MODEL_NAMES) + ') or "module:function" '
        "for your own psi(F, params), which receives params = Lame(mu, lam). The Lamé models "
        "take E, nu or mu, lam; the rubber/tissue models (" + ", ".join(FAMILIES) + ") take "
        "their own keys instead, all required: "
        + "; ".join(f"{n}: {', '.join(k)}" for n, k in FAMILY_KEYS.items())
    )
    E: Positive | None = Field(default=None, description="Young's modulus [Pa] (with nu)")
    nu: Annotated[Number, Field(gt=-1, lt=0.5)] | None = Field(
        default=None, description="Poisson's ratio (with E)"
    )
    mu: Positive | None = Field(
        default=None, description="shear modulus [Pa] (with lam, instead of E, nu)"
    )
    lam: Number | None = Field(
        default=None, description="first Lamé parameter [Pa] (with mu); lam > -mu"
    )
    plane: Literal["strain", "stress"] | None = Field(
        default=None, description='2D only, with E and nu: "strain" (default) or "stress"'
    )
    density: Positive | None = Field(
        default=None, description="[kg/m^3]; required for dynamics and gravity"
    )
    c10: Number | None = Field(default=None, description="[Pa] Mooney–Rivlin, Yeoh (> 0)")
    c01: Number | None = Field(default=None, description="[Pa] Mooney–Rivlin")
    c20: Number | None = Field(default=None, description="[Pa] Yeoh")
    c30: Number | None = Field(default=None, description="[Pa] Yeoh")
    kappa: Number | None = Field(
        default=None, description="bulk modulus [Pa] of the rubber models (> 0)"
    )
    mu1: Number | None = Field(default=None, description="[Pa] Ogden")
    mu2: Number | None = Field(default=None, description="[Pa] Ogden")
    mu3: Number | None = Field(default=None, description="[Pa] Ogden")
    alpha1: Number | None = Field(default=None, description="Ogden exponent")
    alpha2: Number | None = Field(default=None, description="Ogden exponent")
    alpha3: Number | None = Field(default=None, description="Ogden exponent")
    Jm: Number | None = Field(default=None, description="Gent limit of I1bar - 3 (> 0)")
    lambda_m: Number | None = Field(default=None, description="Arruda–Boyce locking stretch (> 0)")
    k1: Number | None = Field(default=None, description="[Pa] HGO fibre stiffness (>= 0)")
    k2: Number | None = Field(default=None, description="HGO fibre stiffening (> 0)")
    kappa_dispersion: Number | None = Field(
        default=None, description="HGO fibre dispersion, in [0, 1/3]"
    )
    bulk: Number | None = Field(default=None, description="[Pa] HGO bulk modulus (> 0)")
    a01: FibreDirection | None = Field(
        default=None,
        description="HGO first fibre direction (reference): a vector for all cells, e.g. "
        '[1, 0, 0]; or per cell: { cell_data = "name" } (a (n_cells, 3) cell-data array of '
        '[mesh].file), regions [{ where = "x < 0.5", direction = [..] }, ..., '
        "{ direction = [..] }] (cell centroids, first match wins, the default last), or the "
        'helix rule of an ellipsoidal ventricle { rule = "helix", endo = 90, epi = -90 } '
        '(and { rule = "transmural" }: its sheet direction)',
    )
    a02: FibreDirection | None = Field(
        default=None, description="HGO second fibre direction (the same forms as a01)"
    )
    # --- Guccione's law (jaxelastic.materials.cardiac) ---
    C: Number | None = Field(default=None, description="[Pa] Guccione stiffness scale (> 0)")
    bf: Number | None = Field(default=None, description="Guccione fibre exponent (> 0)")
    bt: Number | None = Field(default=None, description="Guccione transverse exponent (> 0)")
    bfs: Number | None = Field(
        default=None, description="Guccione fibre–sheet shear exponent (> 0)"
    )
    f0: FibreDirection | None = Field(
        default=None, description="Guccione fibre direction (reference; the same forms as a01)"
    )
    s0: FibreDirection | None = Field(
        default=None,
        description="Guccione sheet direction (the same forms as a01; orthogonalised against "
        "f0, must not be parallel to it)",
    )
    active_tension: NonNegative | None = Field(
        default=None,
        description="[Pa] Guccione only: an active fibre tension T_a >= 0 (second Piola stress "
        "S_a = T_a f0 f0, jaxelastic.materials.with_active_tension), uniform; a static scene "
        "ramps it with [integrator].load_steps together with the loads and pressures, a "
        "dynamic one applies it in full from t = 0",
    )

    @model_validator(mode="after")
    def _one_pair(self):
        if self.active_tension is not None and self.model != "guccione":
            raise fail(
                f"{{at}}.active_tension is a key of 'guccione' (along its f0), not of "
                f"{self.model!r}"
            )
        if self.model in FAMILIES:
            return self._family_keys()
        has_E = self.E is not None or self.nu is not None
        has_mu = self.mu is not None or self.lam is not None
        if has_E == has_mu:
            raise fail("{at} needs either E and nu, or mu and lam (exactly one pair)")
        pair = ("E", "nu") if has_E else ("mu", "lam")
        for k in pair:
            if getattr(self, k) is None:
                raise fail(f"{{at}}.{k} is required (give {pair[0]} and {pair[1]} together)")
        lam, mu = self.lam, self.mu
        if has_mu and lam is not None and mu is not None and not lam > -mu:
            raise fail(f"{{at}}.lam must be > -mu (a positive bulk modulus), got {lam!r}")
        if has_mu and self.plane is not None:
            raise fail("{at}.plane needs E and nu (mu and lam are used as given)")
        stray = [k for k in _all_family_keys() if k != "mu" and getattr(self, k) is not None]
        if stray:
            raise fail(
                f"{{at}}.{stray[0]} is a key of the rubber/tissue models, not of "
                f"{self.model!r} (which takes E, nu or mu, lam)"
            )
        return self

    def _family_keys(self):
        """A rubber/tissue model: exactly its own keys, all given, with valid values."""
        keys = FAMILY_KEYS[self.model]
        for k in ("E", "nu", "lam", "plane", *_all_family_keys()):
            if k not in keys and getattr(self, k) is not None:
                raise fail(
                    f"{{at}}.{k} is not a parameter of {self.model!r} (its keys: {', '.join(keys)})"
                )
        for k in keys:
            v = getattr(self, k)
            if v is None:
                raise fail(f"{{at}}.{k} is required for {self.model!r} (keys: {', '.join(keys)})")
            if k in FAMILY_POSITIVE_KEYS and not v > 0:
                raise fail(f"{{at}}.{k} must be > 0, got {v!r}")
            if k in DIRECTION_KEYS and _is_vector(v) and (len(v) not in (2, 3) or not any(v)):
                raise fail(f"{{at}}.{k} must be a nonzero vector of 2 or 3 numbers, got {list(v)}")
        try:  # the one validation of the family's constants (also used by je.solve)
            check_family(self.model, {k: getattr(self, k) for k in keys})
        except MaterialParameterError as e:
            raise fail(f"{{at}}.{e.key} {e.reason}") from None
        if self.k1 is not None and self.k1 < 0:
            raise fail(f"{{at}}.k1 must be >= 0, got {self.k1!r}")
        kd = self.kappa_dispersion
        if kd is not None and not 0.0 <= kd <= 1.0 / 3.0:
            raise fail(f"{{at}}.kappa_dispersion must lie in [0, 1/3], got {kd!r}")
        return self


def _is_vector(v) -> bool:
    """Whether a fibre direction is one vector (not cell data or regions)."""
    return isinstance(v, tuple) and not any(isinstance(e, BaseModel) for e in v)


def _all_family_keys() -> tuple[str, ...]:
    """Every rubber/tissue parameter key, each once."""
    return tuple(dict.fromkeys(k for keys in FAMILY_KEYS.values() for k in keys))


# ----------------------------------------------------------------------------------------
# node and facet selections, [[dirichlet]], [[traction]], [[point_load]], [gravity]
# ----------------------------------------------------------------------------------------


class PlaneSelector(Table):
    """The nodes on the plane ``X[axis] = value`` (within ``tol``)."""

    axis: Axis = Field(description='0, 1, 2 or "x", "y", "z"')
    value: Number = Field(description="the plane's coordinate [m]")
    tol: Positive | None = Field(
        default=None,
        description="distance tolerance [m] (default: 1e-8 x the largest mesh extent, "
        "at least 1e-8)",
    )


class BoxSelector(Table):
    """The nodes inside the axis-aligned box ``lo <= X <= hi``."""

    lo: Vector = Field(description="lower corner [m]")
    hi: Vector = Field(description="upper corner [m]")

    @model_validator(mode="after")
    def _ordered(self):
        if len(self.lo) != len(self.hi) or any(a > c for a, c in zip(self.lo, self.hi)):  # noqa: B905
            raise fail(
                f"{{at}}: lo must not exceed hi componentwise, got lo={list(self.lo)}, "
                f"hi={list(self.hi)}"
            )
        return self


class Selector(Table):
    """A set of nodes (facets: those whose nodes all match): exactly one of ``plane``,
    ``box``, ``group``, ``where``."""

    plane: PlaneSelector | None = Field(default=None, description="{ axis = ..., value = ... }")
    box: BoxSelector | None = Field(default=None, description="{ lo = [..], hi = [..] }")
    group: Str | None = Field(
        default=None, description="a named group (physical tag) of a mesh file"
    )
    where: WhereExpr | None = Field(
        default=None,
        description='a boolean expression of the rest positions, e.g. "x < 1e-9" or '
        '"(X[:, 0] > 1) & (abs(y) < 0.1)" (see the where-expression rules)',
    )

    @classmethod
    def _prepare(cls, t: dict) -> dict:
        if len(t) != 1:
            raise fail(f"{{at}} needs exactly one of plane, box, group, where; got {sorted(t)}")
        return t


class Rotation(Table):
    """A rigid rotation of the selected nodes, ``u = scale (R (X - c) + c - X)``."""

    axis: Axis = Field(
        default="z", description='rotation axis: 0, 1, 2 or "x", "y", "z" ("z" in 2D)'
    )
    angle_deg: Number = Field(description="rotation angle [degrees]")
    center: Vector | None = Field(default=None, description="a point on the axis [m] (default 0)")
    scale: Number = Field(default=1.0, description="factor applied to the displacement")


class RotateDisplacement(Table):
    """``{ rotate = { ... } }``: a prescribed rotation."""

    rotate: Rotation = Field(description="the rotation")


if TYPE_CHECKING:
    Displacement = Vector | RotateDisplacement | CallableName
else:
    Displacement = either("array", array=Vector, table=RotateDisplacement, str=CallableName)


class DirichletSpec(Table):
    """A prescribed displacement (any number; later entries override earlier ones)."""

    nodes: Selector = Field(description="the constrained nodes")
    components: Annotated[tuple[Axis, ...], Field(min_length=1)] | None = Field(
        default=None, description="the constrained components (default: all)"
    )
    displacement: Displacement | None = Field(
        default=None,
        description='[m]: a vector (default 0), { rotate = { ... } }, or "module:function" '
        "u(X) -> (m, dim) (in dynamics also u(X, t))",
    )
    ramp_time: Positive | None = Field(
        default=None, description="dynamics: the displacement grows linearly until this time [s]"
    )

    @model_validator(mode="after")
    def _distinct(self):
        c = self.components
        if c is not None and len({axis_index(a) for a in c}) != len(c):
            raise fail(f"{{at}}.components repeats a component: {list(c)!r}")
        return self


class _Load(Table):
    _value_key: ClassVar[str] = ""
    if TYPE_CHECKING:  # a field of every subclass
        total_force: Vector | None

    @model_validator(mode="after")
    def _one_value(self):
        k = self._value_key
        if (getattr(self, k) is None) == (self.total_force is None):
            raise fail(f"{{at}} needs exactly one of {k} = [..] or total_force = [..]")
        return self


class TractionSpec(_Load):
    """A dead load per reference area on boundary facets."""

    _value_key: ClassVar[str] = "traction"
    facets: Selector = Field(description="the loaded boundary facets (same selectors as nodes)")
    traction: Vector | None = Field(default=None, description="[Pa] per reference area")
    total_force: Vector | None = Field(default=None, description="[N] spread over the facets' area")


class PointLoadSpec(_Load):
    """Forces on nodes."""

    _value_key: ClassVar[str] = "force"
    nodes: Selector = Field(description="the loaded nodes")
    force: Vector | None = Field(default=None, description="[N] on each node")
    total_force: Vector | None = Field(default=None, description="[N] shared equally by the nodes")


class GravitySpec(Table):
    """A body force ``density * g`` (needs ``[material].density``)."""

    g: Vector = Field(description="gravitational acceleration [m/s^2]")


# ----------------------------------------------------------------------------------------
# [[pressure]] and [[cavity]]: follower pressure on cavity boundaries, cavity volumes
# ----------------------------------------------------------------------------------------


class PressureSpec(Table):
    """A pressure on the deformed boundary facets of a cavity (a follower load, ramped by
    ``[integrator].load_steps`` in statics; in dynamics acting in full from t = 0 unless
    ``ramp_time`` ramps it); conservative for a closed cavity or one whose rim is fixed
    or slides on a symmetry plane through ``origin`` (checked before the solve)."""

    facets: Selector = Field(description="the loaded boundary facets (same selectors as nodes)")
    pressure: Number = Field(
        description="[Pa]; positive pushes against the outward normal, into the body (an "
        "internal pressure inflates the cavity)"
    )
    origin: Vector | None = Field(
        default=None,
        description="[m] the point the opening is closed to (default: the centroid of the "
        "surface's rim); on the symmetry planes a rim slides on",
    )
    cavity: Str | None = Field(
        default=None,
        description="name of the [[cavity]] this surface bounds (its facets must be among "
        "the cavity's; the cavity's origin is the default)",
    )
    follower: bool = Field(
        default=False,
        description="an open surface whose rim moves: the exact follower load without a "
        "potential (Newton with its non-symmetric tangent; see the pressure guide)",
    )
    ramp_time: Positive | None = Field(
        default=None,
        description="dynamics: the pressure grows linearly from 0 until this time [s] "
        "(default: the full pressure from t = 0, a step load)",
    )


class CavitySpec(Table):
    """A cavity whose volume (area in 2D) is reported per load step (dynamics: per output
    frame) in summary.json, with a pressure–volume plot."""

    name: Str = Field(description="the cavity's name (summary.json, [[pressure]].cavity)")
    facets: Selector = Field(description="the boundary facets that bound the cavity")
    origin: Vector | None = Field(
        default=None,
        description="[m] the point the opening is closed to (default: the centroid of the "
        "surface's rim)",
    )
    volume: Positive | None = Field(
        default=None,
        description="[m^3] (2D: m^2) volume control: the cavity is brought to this volume in "
        "the load steps, its wall loaded by the pressure that takes (an unknown; no "
        "[[pressure]] in the scene then)",
    )


class PlaneObstacle(Table):
    """The half-space behind a plane (its normal points to the free side)."""

    point: Vector = Field(description="a point of the plane [m]")
    normal: Vector = Field(description="outward normal (any length)")


class SphereObstacle(Table):
    """A rigid ball (a disc in 2D)."""

    center: Vector = Field(description="center [m]")
    radius: Positive = Field(description="radius [m]")


class ObstacleSpec(Table):
    """A rigid obstacle (barrier contact, IPC): exactly one of ``plane``, ``sphere``, ``box``."""

    plane: PlaneObstacle | None = Field(default=None, description="{ point = [..], normal = [..] }")
    sphere: SphereObstacle | None = Field(
        default=None, description="{ center = [..], radius = .. }"
    )
    box: BoxSelector | None = Field(default=None, description="{ lo = [..], hi = [..] } [m]")
    friction: NonNegative | None = Field(
        default=None, description="Coulomb coefficient mu (default [contact].friction)"
    )
    motion: CallableName | None = Field(
        default=None,
        description='"module:function" t -> (dim,) translation [m] (dynamics: time [s]; '
        "static: the load factor in [0, 1])",
    )

    @model_validator(mode="after")
    def _one_shape(self):
        given = [k for k in ("plane", "sphere", "box") if getattr(self, k) is not None]
        if len(given) != 1:
            raise fail(f"{{at}} needs exactly one of plane, sphere, box; got {given}")
        return self


class ContactSpec(Table):
    """Barrier contact settings (all optional; used when there is an ``[[obstacle]]`` or
    ``self = true``)."""

    self_contact: bool = Field(
        default=False,
        alias="self",
        description="barrier contact of the body's boundary with itself (point-triangle, "
        "edge-edge; 2D point-edge); friction between them: self_friction",
    )
    margin: Positive | None = Field(
        default=None,
        description="self-contact motion bound of one broad phase [m] (default min(10 x dhat, "
        "1/4 of the mean boundary-edge length))",
    )
    dhat: Positive | None = Field(
        default=None, description="barrier reach [m] (default 1e-3 x the bounding-box diagonal)"
    )
    kappa: Positive | None = Field(
        default=None, description="barrier stiffness [N/m] (default: from the elastic stiffness)"
    )
    friction: NonNegative = Field(default=0.0, description="default Coulomb coefficient mu")
    self_friction: NonNegative = Field(
        default=0.0,
        description="Coulomb coefficient mu between self-contact pairs (needs self = true; "
        "IPC's lagged friction, lagged at every load or time step)",
    )


# ----------------------------------------------------------------------------------------
# [solver], [integrator], [output]
# ----------------------------------------------------------------------------------------


class SolverSpec(Table):
    """Newton's method and its linear solver (``jaxelastic.Newton``)."""

    max_steps: Annotated[Integer, Field(ge=1)] = Field(
        default=50, description="Newton iteration limit"
    )
    rtol: NonNegative = Field(default=1e-8, description="relative tolerance on the force residual")
    atol: NonNegative = Field(
        default=0.0, description="absolute tolerance on the force residual [N]"
    )
    xtol: Annotated[Number, Field(ge=0, le=1e-3)] = Field(
        default=1e-12,
        description="also converged when a Newton step moves no node by more than xtol x "
        "the rest bounding-box diagonal (at most 1e-3: a larger one reports unconverged "
        "solves as converged)",
    )
    hessian: Literal["hvp", "element", "projected"] = Field(
        default="element",
        description='"element" (exact element Hessians, assembled), "hvp" (matrix-free '
        'Hessian-vector products) or "projected" (PSD-projected element Hessians)',
    )
    linear: Literal["auto", "cg", "direct", "amg", "multilevel"] = Field(
        default="auto",
        description='"auto" (sparse Cholesky up to 10k dofs in 3D / 100k in 2D, else '
        'AMG-preconditioned CG), "direct", "amg", "multilevel" (device multigrid-'
        'preconditioned CG inside jit, vmap-able) or "cg" (matrix-free PCG inside jit)',
    )
    preconditioner: Literal["block_jacobi", "jacobi", "none"] = Field(
        default="block_jacobi", description='preconditioner of linear = "cg"'
    )
    cg_max_iter: Annotated[Integer, Field(ge=1)] = Field(
        default=2000, description='CG iteration limit per Newton step (linear = "cg")'
    )
    ls_max: Annotated[Integer, Field(ge=1)] = Field(
        default=40, description="maximum step halvings in the line search"
    )
    armijo: Annotated[Number, Field(ge=0, lt=1)] = Field(
        default=1e-4, description="sufficient-decrease constant of the line search"
    )
    require_positive_J: Bool = Field(
        default=False, description="also reject trial steps where an element has J <= 0"
    )
    precision: Literal["float64", "float32"] = Field(
        default="float64",
        description='floating-point precision of the mesh, loads and solve: "float64" or '
        '"float32" (half the memory, faster kernels; Newton stops with SUCCESS at the '
        "residual's round-off floor, recorded as residual_floor)",
    )
    max_memory_gb: Positive | None = Field(
        default=None,
        description="memory budget [GB] for the estimate checked before the build (default: "
        "the memory available); a scene whose estimate exceeds it is refused, a larger value "
        "runs it anyway",
    )
    devices: Annotated[Integer, Field(ge=1)] = Field(
        default=1,
        description="shard the mesh over the first N devices JAX sees (jaxelastic.shard; "
        'N > 1 needs linear = "auto", "cg" or "multilevel"; host CPU devices: '
        "XLA_FLAGS=--xla_force_host_platform_device_count=N)",
    )


class StaticIntegrator(Table):
    """A static solve (the default)."""

    _unknown_suffix: ClassVar[str] = " for type = 'static'"
    type: Literal["static"] = Field(default="static", description='"static" or "dynamic"')
    load_steps: Annotated[Integer, Field(ge=1)] = Field(
        default=1, description="apply the loads in this many equal increments (cut back on failure)"
    )


if TYPE_CHECKING:
    InitialVelocity = Vector | CallableName
else:
    InitialVelocity = either("array", array=Vector, str=CallableName)


MAX_TIME_STEPS = 1_000_000
"""The most time steps (``duration / h``) a dynamic scene may ask for: more is almost
always a unit slip in ``h`` and would run for days without an error."""


class DynamicIntegrator(Table):
    """Time stepping: backward Euler or BDF2 as incremental-potential minimisation."""

    type: Literal["dynamic"] = Field(description='"dynamic"')
    h: Positive = Field(description="time step [s]")
    duration: Positive = Field(description="simulated time [s] (the maximum when settle = true)")
    method: Literal["backward_euler", "bdf2"] = Field(
        default="backward_euler", description='"backward_euler" or "bdf2" (second order)'
    )
    alpha: NonNegative = Field(default=0.0, description="mass-proportional Rayleigh damping [1/s]")
    beta: NonNegative = Field(
        default=0.0, description="stiffness-proportional Rayleigh damping [s]"
    )
    settle: Bool = Field(
        default=False,
        description="stop once kinetic < settle_tol x elastic energy for settle_steps steps",
    )
    settle_tol: Positive = Field(
        default=1e-8, description="kinetic / elastic energy ratio of settle"
    )
    settle_steps: Annotated[Integer, Field(ge=1)] = Field(
        default=5, description="consecutive steps below settle_tol"
    )
    initial_velocity: InitialVelocity | None = Field(
        default=None,
        description='[m/s]: a vector for all nodes, or "module:function" v(X) -> (m, dim) '
        "(default 0; zero on Dirichlet dofs)",
    )
    compare_static: Bool = Field(
        default=False,
        description="also solve the static problem of the final load and report the difference",
    )

    @model_validator(mode="after")
    def _duration(self):
        if self.h < H_MIN:
            raise fail(
                f"{{at}}.h = {self.h!r} s is below {H_MIN:g} s: the inertia term m/h^2 "
                "overflows float64"
            )
        if self.duration < self.h * (1 - 1e-12):
            raise fail(f"{{at}}.duration must be >= h = {self.h!r}, got {self.duration!r}")
        steps = self.duration / self.h
        if steps > MAX_TIME_STEPS:
            raise fail(
                f"{{at}}: duration / h = {steps:.3g} time steps, more than {MAX_TIME_STEPS:.0e}: "
                "raise h (backward Euler and BDF2 are unconditionally stable) or shorten "
                "the duration"
            )
        return self


def _integrator_kind(v) -> str:
    t = v.get("type", "static") if isinstance(v, Mapping) else getattr(v, "type", "static")
    return f"~{t}" if t in ("static", "dynamic") else str(t)


Integrator = Annotated[
    Union[  # noqa: UP007
        Annotated[StaticIntegrator, Tag("~static")], Annotated[DynamicIntegrator, Tag("~dynamic")]
    ],
    Discriminator(_integrator_kind),
]


class OutputSpec(Table):
    """What is written into the output directory besides ``summary.json``."""

    every: Annotated[Integer, Field(ge=1)] = Field(
        default=1, description="write a VTU every k time steps (and the first and last)"
    )
    vtu: Bool = Field(default=True, description="ParaView time series (.vtu files + .pvd)")
    png: Bool = Field(default=True, description="pictures: final shape, tip displacement, energies")
    probes: tuple[Vector, ...] = Field(
        default=(), description="points [m]: report the displacement at the node nearest each"
    )


# ----------------------------------------------------------------------------------------
# [fit]
# ----------------------------------------------------------------------------------------

_E = Annotated[Number, Field(gt=0)]
_NU = Annotated[Number, Field(gt=-1, lt=0.5)]
if TYPE_CHECKING:
    EValues = _E | tuple[_E, ...]
    NuValues = _NU | tuple[_NU, ...]
else:
    EValues = either("scalar", scalar=_E, array=Annotated[tuple[_E, ...], Field(min_length=1)])
    NuValues = either("scalar", scalar=_NU, array=Annotated[tuple[_NU, ...], Field(min_length=1)])


def fit_parameters(model: str) -> tuple[str, ...]:
    """The names ``[fit].fields`` accepts for a material model: E and nu for the Lamé
    models, the scalar parameters of a rubber/tissue model (not fibre directions)."""
    if model in FAMILIES:
        return tuple(k for k in FAMILY_KEYS[model] if k not in DIRECTION_KEYS)
    return ("E", "nu")


def _n_values(x) -> int:
    return len(x) if isinstance(x, tuple) else 1


class FitTarget(Table):
    """Synthetic observations: the scene solved at these "true" parameters."""

    E: EValues = Field(description="true Young's modulus [Pa]: one value, or one per region")
    nu: NuValues = Field(description="true Poisson's ratio: one value, or one per region")
    refine: Annotated[Integer, Field(ge=1)] = Field(
        default=1,
        description="solve the target on a mesh with refine x the cells per axis, observed at "
        "the fitting mesh's nodes (generator meshes only)",
    )


class FitInitial(Table):
    """The initial guess of the fitted parameters, by name (default: the value in
    ``[material]``)."""

    E: EValues | None = Field(default=None, description="[Pa]: one value, or one per region")
    nu: NuValues | None = Field(default=None, description="one value, or one per region")
    mu: Number | None = Field(default=None, description="[Pa] Gent, Arruda–Boyce, HGO")
    c10: Number | None = Field(default=None, description="[Pa] Mooney–Rivlin, Yeoh")
    c01: Number | None = Field(default=None, description="[Pa] Mooney–Rivlin")
    c20: Number | None = Field(default=None, description="[Pa] Yeoh")
    c30: Number | None = Field(default=None, description="[Pa] Yeoh")
    kappa: Number | None = Field(default=None, description="[Pa] bulk modulus, rubber models")
    mu1: Number | None = Field(default=None, description="[Pa] Ogden")
    mu2: Number | None = Field(default=None, description="[Pa] Ogden")
    mu3: Number | None = Field(default=None, description="[Pa] Ogden")
    alpha1: Number | None = Field(default=None, description="Ogden")
    alpha2: Number | None = Field(default=None, description="Ogden")
    alpha3: Number | None = Field(default=None, description="Ogden")
    Jm: Number | None = Field(default=None, description="Gent")
    lambda_m: Number | None = Field(default=None, description="Arruda–Boyce")
    k1: Number | None = Field(default=None, description="[Pa] HGO")
    k2: Number | None = Field(default=None, description="HGO")
    kappa_dispersion: Number | None = Field(default=None, description="HGO")
    bulk: Number | None = Field(default=None, description="[Pa] HGO bulk modulus")


FIT_KINDS = ("positions", "points", "reaction", "moment", "surface", "volume")


class FitObservation(Table):
    """A measurement of a ``[[fit.case]]``, one entry per load factor in its ``file``:
    ``reaction``: CSV with the header ``factor,force`` (force along ``direction`` [N]);
    ``moment``: CSV with the header ``factor,moment`` (the support moment of ``nodes``
    about ``axis`` through ``origin`` [N·m]); ``points``: NPZ with ``points`` (n, dim)
    rest coordinates [m] and ``displacements`` (n_levels, n, dim) [m]; ``positions``: NPZ
    with ``nodes`` (n,) and ``positions`` (n_levels, n, dim) [m]; ``surface``: NPZ with
    ``points`` (n_levels, m, dim) measured deformed positions [m]; ``volume``: CSV with the
    header ``factor,volume`` (the volume of the ``[[cavity]]`` named by ``cavity`` [m^3];
    2D: area per unit thickness [m^2])."""

    kind: Literal["positions", "points", "reaction", "moment", "surface", "volume"] = Field(
        description='"positions", "points" (DIC), "reaction" (force), "moment" (torque), '
        '"surface" (scan) or "volume" (a cavity\'s volume: pressure-volume curves)'
    )
    file: Str = Field(description="data file, relative to the scene (layouts above)")
    sigma: Positive = Field(
        description="standard deviation of one measured value, in the data's units ([m], [N])"
    )
    nodes: Selector | None = Field(
        default=None,
        description="reaction, moment: the supported nodes (the selectors of [[dirichlet]])",
    )
    direction: Vector | None = Field(
        default=None, description="reaction: the direction of the measured force (normalised)"
    )
    axis: Vector | None = Field(
        default=None,
        description="moment, 3D: the axis of the measured moment (normalised); 2D: omit "
        "(the out-of-plane moment)",
    )
    origin: Vector | None = Field(
        default=None, description="moment: a point of the axis [m] (default the origin)"
    )
    components: Annotated[tuple[Literal["x", "y", "z"], ...], Field(min_length=1)] | None = Field(
        default=None, description='points: the measured components, e.g. ["x", "y"] (default all)'
    )
    cavity: Str | None = Field(
        default=None, description="volume: the name of the measured [[cavity]]"
    )

    @model_validator(mode="after")
    def _kind_keys(self):
        reaction, moment = self.kind == "reaction", self.kind == "moment"
        if reaction and (self.nodes is None or self.direction is None):
            raise fail("{at}: kind = 'reaction' needs nodes = { ... } and direction = [..]")
        if moment and self.nodes is None:
            raise fail("{at}: kind = 'moment' needs nodes = { ... } (and axis = [..] in 3D)")
        if not (reaction or moment) and self.nodes is not None:
            raise fail("{at}.nodes belongs to kind = 'reaction' or 'moment' only")
        if not reaction and self.direction is not None:
            raise fail("{at}.direction belongs to kind = 'reaction' only")
        if not moment and (self.axis is not None or self.origin is not None):
            raise fail("{at}: axis and origin belong to kind = 'moment' only")
        if (self.kind == "volume") != (self.cavity is not None):
            raise fail(
                "{at}: kind = 'volume' needs cavity = '<name of a [[cavity]]>'"
                if self.kind == "volume"
                else "{at}.cavity belongs to kind = 'volume' only"
            )
        for k in ("direction", "axis"):
            v = getattr(self, k)
            if v is not None and not any(abs(a) > 0 for a in v):
                raise fail(f"{{at}}.{k} must not be zero")
        if self.components is not None:
            if self.kind != "points":
                raise fail("{at}.components belongs to kind = 'points' only")
            if len(set(self.components)) != len(self.components):
                raise fail(f"{{at}}.components repeats a component: {list(self.components)!r}")
        return self


class FitCase(Table):
    """Another load case: scene overrides, a weight, and its observations (a file of
    positions, or ``[[fit.case.observation]]`` entries over ``load_factors``)."""

    set: dict[str, Any] = Field(
        default={},
        description='dotted-key scene overrides, e.g. { "traction.0.traction" = [2e4, 0, 0] } '
        "(not mesh, integrator or fit)",
    )
    observed: Str | None = Field(
        default=None, description="observation file of this case (file targets)"
    )
    weight: Positive = Field(default=1.0, description="weight of this case in the loss")
    load_factors: Annotated[tuple[Number, ...], Field(min_length=1)] = Field(
        default=(1.0,),
        description="the case's prescribed displacements and loads are multiplied by each "
        "factor in turn (a load path, solved in order), e.g. [0.25, 0.5, 0.75, 1.0]",
    )
    observation: Annotated[list[FitObservation], BeforeValidator(_array_of_tables)] = Field(
        default=[], description="measurements over the load factors ([[fit.case.observation]])"
    )

    @field_validator("set")
    @classmethod
    def _settable(cls, v):
        for path in v:
            if str(path).split(".")[0] in ("mesh", "fit", "integrator"):
                raise fail(f"{{at}}: {path!r} cannot be changed per load case")
        return v


class FitSpec(Table):
    """Material identification (``jaxelastic fit``): fit any parameter of the scene's
    material to observed shapes (synthetic or file targets of E, nu), or to measurements
    of load paths (``[[fit.case.observation]]``)."""

    target: FitTarget | None = Field(
        default=None, description="synthetic observations solved at { E, nu[, refine] }"
    )
    observed: Str | None = Field(
        default=None,
        description="observed positions of the scene's case: .npy (n_nodes, dim), .npz with "
        '"positions" (n_obs, dim) and optional "nodes" (n_obs,), or .csv rows "node, x, y[, z]"',
    )
    initial: FitInitial = Field(
        default=FitInitial(), description="initial guess by name (default: [material])"
    )
    fields: Annotated[tuple[Str, ...], Field(min_length=1)] = Field(
        default=("E", "nu"),
        description='the fitted parameters of the material, e.g. ["E", "nu"] or '
        '["c10", "c01"] (the others stay at [material]); bounds follow each '
        "parameter's meaning",
    )
    regions: tuple[WhereExpr, ...] = Field(
        default=(),
        description="piecewise-constant E, nu: region i = cells whose centroid satisfies the "
        "i-th expression (first match), the last region the rest",
    )
    markers: Annotated[Number, Field(gt=0, le=1)] = Field(
        default=1.0,
        description="fraction of the nodes observed (random, among nodes not fully clamped)",
    )
    noise: NonNegative = Field(
        default=0.0, description="relative Gaussian noise (sigma = noise x RMS displacement)"
    )
    seed: Annotated[Integer, Field(ge=0)] = Field(
        default=0, description="seed of markers and noise"
    )
    optimizer: Literal["lbfgs", "adam", "lm"] = Field(
        default="lbfgs", description='"lbfgs", "adam" or "lm" (Levenberg–Marquardt)'
    )
    learning_rate: Positive = Field(default=0.05, description='step size of "adam"')
    max_iter: Annotated[Integer, Field(ge=0)] = Field(
        default=100, description="optimiser iterations"
    )
    gtol: Positive = Field(
        default=1e-10, description="stop when the gradient norm (unconstrained variables) is below"
    )
    atol: NonNegative = Field(
        default=1e-12,
        description='optimizer = "lm": also converged when a Gauss-Newton step predicts a '
        "decrease of the cost (chi2 / 2, residuals in units of sigma) below this: then the "
        "parameters lie within sqrt(2 atol) standard errors of the optimum (an exact fit to "
        "noise-free data is recognised instead of stalling at round-off)",
    )
    case: Annotated[list[FitCase], BeforeValidator(_array_of_tables)] = Field(
        default=[], description="more load cases ([[fit.case]])"
    )

    @property
    def measured(self) -> bool:
        """Whether the fit uses ``[[fit.case.observation]]`` measurements."""
        return any(c.observation for c in self.case)

    @model_validator(mode="after")
    def _consistent(self):
        if self.measured:
            return self._consistent_measured()
        if (self.target is None) == (self.observed is None):
            raise fail("{at} needs exactly one of target = { E, nu } (synthetic) or observed")
        if len(set(self.fields)) != len(self.fields):
            raise fail(f"{{at}}.fields has duplicates: {list(self.fields)!r}")
        n_reg = len(self.regions) + 1 if self.regions else 1
        for sec in ("target", "initial"):
            t = getattr(self, sec)
            for k in ("E", "nu"):
                val = None if t is None else getattr(t, k)
                if val is not None and _n_values(val) not in (1, n_reg):
                    raise fail(
                        f"{{at}}.{sec}.{k} must have 1 or {n_reg} values (one per region), "
                        f"got {_n_values(val)}"
                    )
        for i, c in enumerate(self.case):
            key = f"[fit.case][{i}]"
            if c.observed is not None and self.target is not None:
                raise fail(f"{key}.observed: not with a synthetic [fit].target")
            if c.observed is None and self.observed is not None:
                raise fail(f"{key}.observed is required (the scene's targets come from files)")
            if c.load_factors != (1.0,):
                raise fail(f"{key}.load_factors needs [[fit.case.observation]] measurements")
        return self

    def _consistent_measured(self):
        for k in ("target", "observed"):
            if getattr(self, k) is not None:
                raise fail(f"{{at}}.{k}: not with [[fit.case.observation]] measurements")
        if self.regions:
            raise fail("{at}.regions: not with [[fit.case.observation]] measurements")
        for i, c in enumerate(self.case):
            key = f"[fit.case][{i}]"
            if not c.observation:
                raise fail(f"{key} has no [[fit.case.observation]] (every case needs one)")
            if c.observed is not None:
                raise fail(f"{key}.observed: use [[fit.case.observation]] kind = 'positions'")
        if len(set(self.fields)) != len(self.fields):
            raise fail(f"{{at}}.fields has duplicates: {list(self.fields)!r}")
        return self


# ----------------------------------------------------------------------------------------
# the scene file
# ----------------------------------------------------------------------------------------


def _scene_name(v: str) -> str:
    """A scene name is a name: it becomes the output directory ``jaxelastic-out/<name>``
    without ``--out``, so no path separator, no ``.``/``..``, no leading dot or ``~``, no
    control characters, at most 100 characters."""
    bad = (
        not v.strip()
        or len(v) > 100
        or any(c in v for c in "/\\:")
        or v.startswith((".", "~"))
        or any(ord(c) < 32 or ord(c) == 127 for c in v)
    )
    if bad:
        raise fail(
            f"{{at}} must be a name, not a path: 1 to 100 characters without '/', '\\', ':', "
            f"control characters or a leading '.' or '~', got {v!r} (it names the output "
            "directory jaxelastic-out/<name>; use --out to write elsewhere)"
        )
    return v


SceneName = Annotated[str, Strict(), AfterValidator(_scene_name)]
"""The scene's ``name``: a file name (:func:`_scene_name`)."""


class SceneSpec(Table):
    """A jaxelastic scene file."""

    name: SceneName = Field(
        default="scene",
        description="label (output directory name, plot titles): a name, not a path",
    )
    description: Str = Field(default="", description="one line shown by `jaxelastic scenes`")
    mesh: MeshSpec = Field(description="the mesh")
    material: MaterialSpec = Field(description="the material")
    dirichlet: Annotated[list[DirichletSpec], BeforeValidator(_array_of_tables)] = Field(
        default=[], description="prescribed displacements ([[dirichlet]])"
    )
    traction: Annotated[list[TractionSpec], BeforeValidator(_array_of_tables)] = Field(
        default=[], description="surface loads ([[traction]])"
    )
    point_load: Annotated[list[PointLoadSpec], BeforeValidator(_array_of_tables)] = Field(
        default=[], description="nodal forces ([[point_load]])"
    )
    gravity: GravitySpec | None = Field(default=None, description="gravity")
    pressure: Annotated[list[PressureSpec], BeforeValidator(_array_of_tables)] = Field(
        default=[], description="follower pressures on cavity boundaries ([[pressure]])"
    )
    cavity: Annotated[list[CavitySpec], BeforeValidator(_array_of_tables)] = Field(
        default=[], description="cavities whose volume is reported ([[cavity]])"
    )
    obstacle: Annotated[list[ObstacleSpec], BeforeValidator(_array_of_tables)] = Field(
        default=[], description="rigid obstacles with barrier contact ([[obstacle]])"
    )
    contact: ContactSpec | None = Field(default=None, description="contact settings")
    solver: SolverSpec = Field(default=SolverSpec(), description="the Newton solver")
    integrator: Integrator = Field(
        default=StaticIntegrator(), description="static (default) or dynamic"
    )
    output: OutputSpec = Field(default=OutputSpec(), description="outputs")
    fit: FitSpec | None = Field(
        default=None, description="material identification (jaxelastic fit)"
    )

    @classmethod
    def _unknown_key(cls, key: str, valid: list) -> str:
        return f"unknown top-level key {key!r} (valid: {', '.join(valid)})"

    @classmethod
    def _prepare(cls, t: dict) -> dict:
        for k in ("mesh", "material"):
            if k not in t:
                raise fail(f"[{k}] is required")
        fit, mat = t.get("fit"), t.get("material")
        if isinstance(fit, Mapping) and isinstance(mat, Mapping):  # initial guess: [material]
            init = fit.get("initial", {})
            if isinstance(init, Mapping):
                ok = lambda v: isinstance(v, (int, float, list, tuple)) and not isinstance(v, bool)
                keys = FitInitial.model_fields
                init = {k: mat[k] for k in keys if ok(mat.get(k))} | dict(init)
                t["fit"] = {**fit, "initial": init}
        return t

    def _fit_fields_problem(self) -> str | None:
        """An unknown ``[fit].fields`` name or a missing initial value, or None."""
        fit, model = self.fit, self.material.model
        assert fit is not None
        if self.material.active_tension is not None:
            return (
                "[fit] with [material].active_tension: a fit identifies passive constants; "
                "leave active_tension out of a [fit] scene"
            )
        valid = fit_parameters(model)
        if model in FAMILIES and not fit.measured:
            return (
                f"[fit] with a target of positions fits E and nu: it needs a Lamé model, not "
                f"{model!r}; fit {', '.join(valid)} with [[fit.case.observation]] measurements"
            )
        for k in fit.fields:
            if k not in valid:
                return (
                    f"[fit].fields: {k!r} is not a parameter of {model!r} (fittable: "
                    f"{', '.join(valid)})"
                )
        needed = ("E", "nu") if model not in FAMILIES else fit.fields
        for k in needed:
            if getattr(fit.initial, k) is None:
                return f"[fit].initial.{k} is required ([material] has no {k})"
        names = [c.name for c in self.cavity]
        for i, case in enumerate(fit.case):
            for j, o in enumerate(case.observation):
                if o.cavity is not None and o.cavity not in names:
                    return (
                        f"[fit.case][{i}].observation[{j}].cavity {o.cavity!r} names no "
                        f"[[cavity]] (cavities: {', '.join(repr(n) for n in names) or 'none'})"
                    )
        return None

    @property
    def static(self) -> bool:
        """Whether the scene is static (``[integrator].type = "static"``)."""
        return self.integrator.type == "static"

    @property
    def known_dim(self) -> int | None:
        """The spatial dimension when a generator fixes it, else None (a mesh file)."""
        generator = self.mesh.generator
        return None if generator is None else GENERATOR_DIM.get(generator)

    @model_validator(mode="after")
    def _consistent(self):
        problem = self._cross_problem()
        if problem is None and self.known_dim is not None:
            problem = self.dim_problem(self.known_dim)
        if problem is not None:
            raise fail(problem)
        return self

    def _cross_problem(self) -> str | None:
        """The first inconsistency between tables, or None."""
        dynamic = not self.static
        if self.fit is not None:
            problem = self._fit_fields_problem()
            if problem is not None:
                return problem
            if self.fit.target is not None and self.fit.target.refine > 1:
                if self.mesh.generator is None:
                    return "[fit].target.refine needs a [mesh].generator (not a mesh file)"
            if dynamic:
                return "[fit] needs a static scene ([integrator].type = 'static')"
        n_dev, linear = self.solver.devices, self.solver.linear
        if n_dev > 1 and self.fit is not None:
            return f"[solver].devices = {n_dev}: a [fit] scene runs on one device (devices = 1)"
        if n_dev > 1 and linear in ("direct", "amg"):
            return (
                f'[solver].devices = {n_dev}: linear = "{linear}" is a host solver and cannot '
                'run sharded; use linear = "auto", "cg" or "multilevel"'
            )
        problem = self._pressure_problem()
        if problem is not None:
            return problem
        if self.material.density is None:
            if dynamic:
                return "[material].density is required for a dynamic scene"
            if self.gravity is not None:
                return "[material].density is required with [gravity]"
        if dynamic:
            return None
        if not self.dirichlet:
            return (
                "[dirichlet]: a static scene needs at least one Dirichlet condition "
                "(else rigid motions are free)"
            )
        for i, d in enumerate(self.dirichlet):
            if d.ramp_time is not None:
                return f"[dirichlet][{i}].ramp_time is only valid in a dynamic scene"
        return None

    def _pressure_problem(self) -> str | None:
        """The first inconsistency of [[pressure]] and [[cavity]], or None."""
        names = [c.name for c in self.cavity]
        for i, n in enumerate(names):
            if n in names[:i]:
                return f"[cavity][{i}].name {n!r} is used twice"
        for i, p in enumerate(self.pressure):
            if p.cavity is not None and p.cavity not in names:
                return (
                    f"[pressure][{i}].cavity {p.cavity!r} names no [[cavity]] (cavities: "
                    f"{', '.join(repr(n) for n in names) or 'none'})"
                )
        controlled = [c.name for c in self.cavity if c.volume is not None]
        if controlled and self.pressure:
            return (
                f"[cavity] {controlled[0]!r} has a volume (volume control: its pressure is the "
                "unknown); a scene with volume control has no [[pressure]] entries"
            )
        which = "[[pressure]]" if self.pressure else "[[cavity]]"
        if controlled and not self.static:
            return (
                f"[cavity] {controlled[0]!r} has a volume: volume control is supported in "
                "static scenes ([integrator].type = 'static')"
            )
        for i, p in enumerate(self.pressure):
            if p.ramp_time is not None and self.static:
                return f"[pressure][{i}].ramp_time is only valid in a dynamic scene"
        if (self.pressure or self.cavity) and self.solver.devices > 1:
            return f"{which} runs on one device ([solver].devices = 1)"
        return None

    def dim_problem(self, dim: int) -> str | None:
        """The first vector length or axis that does not fit a ``dim``-D mesh, or None."""
        if dim == 3 and self.material.plane is not None:
            return "[material].plane applies to 2D meshes only"
        for kind, key, val in self._dim_items():
            if kind == "vec" and len(val) != dim:
                return f"{key} must have {dim} components (the mesh is {dim}D), got {len(val)}"
            a = axis_index(val) if kind != "vec" else 0
            if kind == "axis" and a >= dim:
                return f"{key} must be an axis of a {dim}D mesh (0..{dim - 1}), got {a}"
            if kind == "rotate" and dim == 2 and a != 2:
                return f"{key}.axis must be 'z' (2) in 2D, got {a}"
        return None

    def _dim_items(self) -> Iterator[tuple[str, str, Any]]:
        """``(kind, key, value)`` of every dimension-dependent entry, in file order."""
        m = self.mesh
        for k in ("size", "origin"):
            if getattr(m, k) is not None and m.generator != "cook":
                yield "vec", f"[mesh].{k}", getattr(m, k)
        for i, d in enumerate(self.dirichlet):
            key = f"[dirichlet][{i}]"
            yield from _selector_items(f"{key}.nodes", d.nodes)
            for j, a in enumerate(d.components or ()):
                yield "axis", f"{key}.components[{j}]", a
            u = d.displacement
            if isinstance(u, tuple):
                yield "vec", f"{key}.displacement", u
            elif isinstance(u, RotateDisplacement):
                r = u.rotate
                if r.center is not None:
                    yield "vec", f"{key}.displacement.rotate.center", r.center
                yield "rotate", f"{key}.displacement.rotate", r.axis
        for sec, where, loads_ in (
            ("traction", "facets", self.traction),
            ("point_load", "nodes", self.point_load),
        ):
            for i, ld in enumerate(loads_):
                key = f"[{sec}][{i}]"
                yield from _selector_items(f"{key}.{where}", getattr(ld, where))
                for k in (ld._value_key, "total_force"):
                    if getattr(ld, k) is not None:
                        yield "vec", f"{key}.{k}", getattr(ld, k)
        if self.gravity is not None:
            yield "vec", "[gravity].g", self.gravity.g
        for sec, items in (("pressure", self.pressure), ("cavity", self.cavity)):
            for i, ps in enumerate(items):
                yield from _selector_items(f"[{sec}][{i}].facets", ps.facets)
                if ps.origin is not None:
                    yield "vec", f"[{sec}][{i}].origin", ps.origin
        for i, ob in enumerate(self.obstacle):
            for shape in ("plane", "sphere", "box"):
                spec = getattr(ob, shape)
                for k, v in ({} if spec is None else spec.model_dump()).items():
                    if isinstance(v, tuple):
                        yield "vec", f"[obstacle][{i}].{shape}.{k}", v
        iv = getattr(self.integrator, "initial_velocity", None)
        if isinstance(iv, tuple):
            yield "vec", "[integrator].initial_velocity", iv
        for i, p in enumerate(self.output.probes):
            yield "vec", f"[output].probes[{i}]", p


def _selector_items(key: str, sel: Selector):
    if sel.plane is not None:
        yield "axis", f"{key}.plane.axis", sel.plane.axis
    if sel.box is not None:
        yield "vec", f"{key}.box.lo", sel.box.lo
        yield "vec", f"{key}.box.hi", sel.box.hi


# ----------------------------------------------------------------------------------------
# entry points
# ----------------------------------------------------------------------------------------


def validate(raw: Mapping, label: str, base_dir: str) -> SceneSpec:
    """Validate a raw scene (a dict as read from TOML).

    Args:
        raw: the scene; lists and tuples are both accepted for arrays.
        label: how messages name the scene (a file name, or ``"<dict>"``).
        base_dir: directory for relative mesh paths and ``module:function`` imports.
    Raises:
        SceneError: the first problems, each naming the key, the value and what is valid.
    """
    try:
        spec = SceneSpec.model_validate(raw, context={"base_dir": base_dir})
    except ValidationError as e:
        raise from_validation_error(label, e) from None
    _check_user_displacements(spec, label, base_dir)
    return spec


def _check_user_displacements(spec: SceneSpec, label: str, base_dir: str) -> None:
    """A static scene's ``displacement = "module:function"`` must accept ``u(X)``."""
    if not spec.static:
        return
    for i, d in enumerate(spec.dirichlet):
        if isinstance(d.displacement, str):
            fn = import_callable(d.displacement, base_dir)
            if n_positional(fn) < 1:
                raise SceneError(
                    f"scene {label!r}: [dirichlet][{i}].displacement: {d.displacement!r} "
                    "must accept u(X)"
                )


def _tidy(node):
    """TOML has no null: optional keys are simply absent, so drop ``null`` alternatives,
    ``default: null`` and pydantic's generated titles."""
    if isinstance(node, list):
        return [_tidy(v) for v in node]
    if not isinstance(node, dict):
        return node
    out = {k: _tidy(v) for k, v in node.items() if k != "title" or not isinstance(v, str)}
    if out.get("default", 0) is None:
        del out["default"]
    for key in ("anyOf", "oneOf"):
        alts = [a for a in out.get(key, ()) if a != {"type": "null"}]
        if key in out and len(alts) == 1:
            del out[key]
            out = {**alts[0], **out}
        elif key in out:
            out[key] = alts
    return out


def json_schema() -> dict:
    """The JSON Schema (draft 2020-12) of a scene file, for editors and validators
    (``jaxelastic schema > scene.schema.json``)."""
    schema = _tidy(SceneSpec.model_json_schema())
    schema["$defs"] = {k: {"title": k, **v} for k, v in schema["$defs"].items()}
    return {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": "jaxelastic scene",
        **schema,
    }
