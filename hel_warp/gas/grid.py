"""The Cartesian grid and the analytic flow geometry (fixed data, built once).

- ``Grid``: uniform spacing ``h`` on all axes, ``origin`` (m), ``shape`` (nx, ny, nz), a
  periodic flag per axis. Cell ``(i, j, k)`` has its centre at ``origin + (i+1/2, j+1/2, k+1/2) h``.
- ``Geometry``: a union of ``Box`` (axis-aligned), ``Channel`` (rectangular cross-section
  along any direction) and ``Cylinder`` (circular cross-section, capped) shapes, signed distance negative inside the fluid
  (``kernels/sdf.py``), and named ``Patch``es (inlet at a fixed velocity vector, outlet at
  a fixed pressure) on the domain boundary.
- ``FlowDomain``: what the gas solver needs on the device: the fluid mask and the MAC face
  types and boundary values; built by ``Geometry.build(grid)``, which also rejects a grid
  too coarse for the geometry with a ``ConfigError`` that names the spacing to use.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from hel_warp.errors import ConfigError, require_finite, require_positive
from kernels import gas as gas_kernels
from kernels import sdf as sdf_kernels

MIN_CELLS_ACROSS = 3
"""Fewest cells a channel or box must span across its cross-section."""

AXES = "xyz"


def _vec(name: str, value, length: int = 3) -> tuple:
    arr = np.asarray(value, dtype=np.float64).reshape(-1)
    if arr.size != length:
        raise ConfigError(f"{name} must have {length} components (got {value!r})")
    require_finite(name, arr)
    return tuple(float(v) for v in arr)


@dataclass(frozen=True, kw_only=True)
class Grid:
    """Uniform Cartesian grid."""

    origin: tuple = (0.0, 0.0, 0.0)
    """Lower corner of the domain, m."""
    spacing: float = 1.0e-3
    """Cell size h, m (same on all axes)."""
    shape: tuple = (8, 8, 8)
    """Number of cells (nx, ny, nz)."""
    periodic: tuple = (False, False, False)
    """Periodic flag per axis."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "origin", _vec("grid origin", self.origin))
        require_positive("grid spacing", self.spacing, "m")
        shape = tuple(int(n) for n in self.shape)
        if len(shape) != 3 or any(n < 1 for n in shape) or shape != tuple(self.shape):
            raise ConfigError(f"grid shape must be three positive integers (got {self.shape!r})")
        object.__setattr__(self, "shape", shape)
        periodic = tuple(bool(p) for p in self.periodic)
        if len(periodic) != 3:
            raise ConfigError(f"grid periodic must have three flags (got {self.periodic!r})")
        object.__setattr__(self, "periodic", periodic)
        for axis in range(3):
            if periodic[axis] and shape[axis] < 3:
                raise ConfigError(f"periodic axis {AXES[axis]} needs >= 3 cells (got {shape[axis]})")

    @property
    def cell_volume(self) -> float:
        """h^3, m^3."""
        return self.spacing**3

    @property
    def upper(self) -> tuple:
        """Upper corner of the domain, m."""
        return tuple(o + n * self.spacing for o, n in zip(self.origin, self.shape))

    def cell_centres(self) -> np.ndarray:
        """Cell centres, float64 array of shape (nx, ny, nz, 3), m (host side, for set-up and tests)."""
        axes = [self.origin[a] + (np.arange(self.shape[a]) + 0.5) * self.spacing for a in range(3)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)

    def info(self) -> gas_kernels.GridInfo:
        info = gas_kernels.GridInfo()
        info.origin = wp.vec3(*self.origin)
        info.spacing = float(self.spacing)
        info.shape = wp.vec3i(*self.shape)
        info.periodic = wp.vec3i(*(int(p) for p in self.periodic))
        return info


@dataclass(frozen=True, kw_only=True)
class Box:
    """Axis-aligned box of fluid between corners ``lo`` and ``hi`` (m)."""

    lo: tuple
    hi: tuple
    name: str = "box"

    def __post_init__(self) -> None:
        object.__setattr__(self, "lo", _vec(f"{self.name} lo", self.lo))
        object.__setattr__(self, "hi", _vec(f"{self.name} hi", self.hi))
        if any(h <= l for l, h in zip(self.lo, self.hi)):
            raise ConfigError(f"{self.name}: hi must exceed lo on every axis (got lo={self.lo}, hi={self.hi})")

    def oriented(self) -> tuple:
        """(centre, rotation rows, half extents, names of the cross-section sizes checked)."""
        lo, hi = np.array(self.lo), np.array(self.hi)
        return 0.5 * (lo + hi), np.eye(3), 0.5 * (hi - lo), (0, 1, 2)


@dataclass(frozen=True, kw_only=True)
class Channel:
    """Straight channel of rectangular cross-section from ``start`` to ``end`` (m).

    ``width`` is measured along ``up x direction`` and ``height`` along the part of ``up``
    normal to the direction (default ``up``: z, or y for a channel along z).
    """

    start: tuple
    end: tuple
    width: float
    height: float
    up: tuple | None = None
    name: str = "channel"

    def __post_init__(self) -> None:
        object.__setattr__(self, "start", _vec(f"{self.name} start", self.start))
        object.__setattr__(self, "end", _vec(f"{self.name} end", self.end))
        require_positive(f"{self.name} width", self.width, "m")
        require_positive(f"{self.name} height", self.height, "m")
        if np.linalg.norm(np.subtract(self.end, self.start)) == 0.0:
            raise ConfigError(f"{self.name}: start and end coincide; give a channel of non-zero length")
        if self.up is not None:
            object.__setattr__(self, "up", _vec(f"{self.name} up", self.up))

    def axes(self) -> np.ndarray:
        """Rows: direction, width direction, height direction (orthonormal, right-handed)."""
        d = np.subtract(self.end, self.start)
        d = d / np.linalg.norm(d)
        up = np.array(self.up if self.up is not None else ((0.0, 1.0, 0.0) if abs(d[2]) > 0.9 else (0.0, 0.0, 1.0)))
        e3 = up - np.dot(up, d) * d
        if np.linalg.norm(e3) < 1e-9:
            raise ConfigError(f"{self.name}: 'up' is parallel to the channel direction; give another up vector")
        e3 /= np.linalg.norm(e3)
        e2 = np.cross(e3, d)
        return np.stack([d, e2, e3])

    def oriented(self) -> tuple:
        length = float(np.linalg.norm(np.subtract(self.end, self.start)))
        centre = 0.5 * (np.array(self.start) + np.array(self.end))
        return centre, self.axes(), np.array([0.5 * length, 0.5 * self.width, 0.5 * self.height]), (1, 2)


@dataclass(frozen=True, kw_only=True)
class Cylinder:
    """Capped circular cylinder of fluid of ``radius`` (m) from ``start`` to ``end`` (m), e.g. a riser or a
    round column; on the Cartesian grid its wall is stair-stepped, as every wall."""

    start: tuple
    end: tuple
    radius: float
    name: str = "cylinder"
    kind = 1
    """``kernels.sdf.SHAPE_CYLINDER``."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "start", _vec(f"{self.name} start", self.start))
        object.__setattr__(self, "end", _vec(f"{self.name} end", self.end))
        require_positive(f"{self.name} radius", self.radius, "m")
        if np.linalg.norm(np.subtract(self.end, self.start)) == 0.0:
            raise ConfigError(f"{self.name}: start and end coincide; give a cylinder of non-zero length")

    def oriented(self) -> tuple:
        d = np.subtract(self.end, self.start)
        length = float(np.linalg.norm(d))
        d = d / length
        aux_axis = np.array((0.0, 0.0, 1.0)) if abs(d[2]) < 0.9 else np.array((0.0, 1.0, 0.0))
        e2 = np.cross(aux_axis, d)
        e2 /= np.linalg.norm(e2)
        e3 = np.cross(d, e2)
        centre = 0.5 * (np.array(self.start) + np.array(self.end))
        return centre, np.stack([d, e2, e3]), np.array([0.5 * length, self.radius, self.radius]), (1, 2)


@dataclass(frozen=True, kw_only=True)
class Patch:
    """A named boundary patch: the faces of the domain side ``axis``/``side`` whose centres lie in
    the region ``lo``..``hi`` (the ``axis`` component of lo/hi is ignored) next to fluid cells."""

    name: str
    kind: str
    """'inlet' (fixed velocity vector) or 'outlet' (fixed pressure)."""
    axis: int
    """0, 1, 2 for x, y, z."""
    side: str
    """'min' or 'max' end of the axis."""
    lo: tuple = (-math.inf, -math.inf, -math.inf)
    hi: tuple = (math.inf, math.inf, math.inf)
    velocity: tuple = (0.0, 0.0, 0.0)
    """Inlet velocity vector, m/s; its normal component must point into the domain."""
    pressure: float = 0.0
    """Outlet (modified) pressure p', Pa."""

    def __post_init__(self) -> None:
        if self.kind not in ("inlet", "outlet"):
            raise ConfigError(f"patch {self.name!r}: kind must be 'inlet' or 'outlet' (got {self.kind!r})")
        if self.axis not in (0, 1, 2):
            raise ConfigError(f"patch {self.name!r}: axis must be 0, 1 or 2 (got {self.axis!r})")
        if self.side not in ("min", "max"):
            raise ConfigError(f"patch {self.name!r}: side must be 'min' or 'max' (got {self.side!r})")
        object.__setattr__(self, "lo", tuple(float(v) for v in self.lo))
        object.__setattr__(self, "hi", tuple(float(v) for v in self.hi))
        object.__setattr__(self, "velocity", _vec(f"patch {self.name} velocity", self.velocity))
        require_finite(f"patch {self.name} pressure", self.pressure)
        if self.kind == "inlet":
            inward = self.velocity[self.axis] * (1.0 if self.side == "min" else -1.0)
            if not inward > 0.0:
                raise ConfigError(f"inlet {self.name!r}: velocity {self.velocity} must point into the domain "
                                  f"({'+' if self.side == 'min' else '-'}{AXES[self.axis]} on the {self.side} side)")


@dataclass(frozen=True)
class FlowDomain:
    """Device-side fixed data of the gas solver (see ``kernels/gas.py`` for the face layout)."""

    grid: Grid
    geometry: "Geometry"
    cell_fluid: wp.array
    """int32 (nx, ny, nz): 1 fluid, 0 solid."""
    face_type: gas_kernels.FaceInt
    """Face types FACE_WALL/FLUID/INLET/OUTLET/ALIAS per axis."""
    face_bc: gas_kernels.FaceBc
    """Inlet velocity vectors and outlet pressures on the faces."""
    patch_faces: dict = field(default_factory=dict)
    """name -> (axis, boolean numpy mask over that axis's faces), for fluxes and tests."""

    @property
    def has_outlet(self) -> bool:
        return any(p.kind == "outlet" for p in self.geometry.patches)

    def patch_mass_flow(self, name: str, face_velocity: tuple, face_eps: tuple | None = None,
                        density: float = 1.0) -> float:
        """Mass flow (kg/s) leaving the domain through patch ``name`` (negative = entering).

        ``face_velocity``/``face_eps``: numpy arrays per axis (as ``GasField.face_arrays()``).
        Host-side diagnostic, not for the time loop.
        """
        axis, mask = self.patch_faces[name]
        patch = next(p for p in self.geometry.patches if p.name == name)
        sign = 1.0 if patch.side == "max" else -1.0
        eps = 1.0 if face_eps is None else face_eps[axis][mask]
        return float(sign * density * np.sum(eps * face_velocity[axis][mask]) * self.grid.spacing**2)


@dataclass(frozen=True)
class Geometry:
    """Union of fluid shapes plus boundary patches. ``Geometry.build(grid)`` makes a ``FlowDomain``."""

    shapes: tuple
    patches: tuple = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "shapes", tuple(self.shapes))
        object.__setattr__(self, "patches", tuple(self.patches))
        if not self.shapes:
            raise ConfigError("geometry needs at least one Box, Channel or Cylinder")
        names = [p.name for p in self.patches]
        if len(set(names)) != len(names):
            raise ConfigError(f"patch names must be unique (got {names})")

    def shapes_struct(self, device=None) -> sdf_kernels.SdfShapes:
        """The shapes as ``kernels.sdf.SdfShapes`` for ``sdf_union`` / ``sdf_union_normal``."""
        data = [s.oriented() for s in self.shapes]
        shapes = sdf_kernels.SdfShapes()
        shapes.center = wp.array(np.array([d[0] for d in data]), dtype=wp.vec3, device=device)
        shapes.rotation = wp.array(np.array([d[1] for d in data]), dtype=wp.mat33, device=device)
        shapes.half_extent = wp.array(np.array([d[2] for d in data]), dtype=wp.vec3, device=device)
        shapes.kind = wp.array(np.array([getattr(s, "kind", 0) for s in self.shapes], np.int32), dtype=wp.int32,
                               device=device)
        shapes.count = len(data)
        return shapes

    def check_resolution(self, grid: Grid) -> None:
        """ConfigError when a shape's cross-section spans fewer than MIN_CELLS_ACROSS cells."""
        h = grid.spacing
        for shape in self.shapes:
            _, _, half, checked = shape.oriented()
            narrowest = min(2.0 * half[a] for a in checked)
            if narrowest < MIN_CELLS_ACROSS * h * (1.0 - 1e-9):
                raise ConfigError(
                    f"grid spacing {h:.4g} m is too coarse for {shape.name!r}: its narrowest side "
                    f"{narrowest:.4g} m spans {narrowest / h:.2f} cells (need >= {MIN_CELLS_ACROSS}); "
                    f"use spacing <= {narrowest / MIN_CELLS_ACROSS:.4g} m")

    def build(self, grid: Grid, device=None) -> FlowDomain:
        """Fluid mask (SDF at cell centres < 0) and MAC face types / boundary values."""
        self.check_resolution(grid)
        for patch in self.patches:
            if grid.periodic[patch.axis]:
                raise ConfigError(f"patch {patch.name!r} lies on periodic axis {AXES[patch.axis]}; "
                                  "make that axis non-periodic or drop the patch")
        kinds = {p.kind for p in self.patches}
        if "inlet" in kinds and "outlet" not in kinds:
            raise ConfigError("the geometry has an inlet but no outlet: the gas cannot leave; add an outlet patch")

        shapes = self.shapes_struct(device)
        cell_fluid = wp.zeros(grid.shape, dtype=wp.int32, device=device)
        sdf_kernels.eval_fluid_mask(shapes, grid.origin, grid.spacing, cell_fluid)
        fluid = cell_fluid.numpy().astype(bool)
        if not fluid.any():
            raise ConfigError("no cell centre lies inside the geometry: check that the shapes overlap the grid "
                              f"(origin {grid.origin}, upper {grid.upper})")

        h = grid.spacing
        types, bc_vel, bc_p, patch_faces = [], [], [], {}
        for axis in range(3):
            fshape = list(grid.shape)
            fshape[axis] += 1
            t = np.full(fshape, int(gas_kernels.FACE_WALL), dtype=np.int32)
            vel = np.zeros(fshape + [3], dtype=np.float32)
            pres = np.zeros(fshape, dtype=np.float32)
            lo_cells = [slice(None)] * 3
            lo_cells[axis] = slice(0, -1)
            hi_cells = [slice(None)] * 3
            hi_cells[axis] = slice(1, None)
            inner = [slice(None)] * 3
            inner[axis] = slice(1, -1)
            both = fluid[tuple(lo_cells)] & fluid[tuple(hi_cells)]
            t[tuple(inner)] = np.where(both, int(gas_kernels.FACE_FLUID), int(gas_kernels.FACE_WALL))
            first = [slice(None)] * 3
            first[axis] = 0
            last = [slice(None)] * 3
            last[axis] = -1
            if grid.periodic[axis]:
                wrap = fluid[tuple(first)] & fluid[tuple(last)]
                t[tuple(first)] = np.where(wrap, int(gas_kernels.FACE_FLUID), int(gas_kernels.FACE_WALL))
                t[tuple(last)] = int(gas_kernels.FACE_ALIAS)
            types.append(t)
            bc_vel.append(vel)
            bc_p.append(pres)

        for patch in self.patches:
            axis = patch.axis
            t, vel, pres = types[axis], bc_vel[axis], bc_p[axis]
            index = 0 if patch.side == "min" else grid.shape[axis]
            cell_index = 0 if patch.side == "min" else grid.shape[axis] - 1
            slab = [slice(None)] * 3
            slab[axis] = index
            cell_slab = [slice(None)] * 3
            cell_slab[axis] = cell_index
            centres = grid.cell_centres()[tuple(cell_slab)]  # 2D x 3
            inside = np.ones(centres.shape[:2], dtype=bool)
            for other in range(3):
                if other == axis:
                    continue
                inside &= (centres[..., other] >= patch.lo[other]) & (centres[..., other] <= patch.hi[other])
            selected = inside & fluid[tuple(cell_slab)]
            if not selected.any():
                extents = [patch.hi[o] - patch.lo[o] for o in range(3) if o != axis]
                finite = [e for e in extents if math.isfinite(e)]
                hint = (f"use spacing <= {min(finite) / MIN_CELLS_ACROSS:.4g} m or " if finite else "")
                raise ConfigError(f"patch {patch.name!r} covers no fluid cell at grid spacing {h:.4g} m "
                                  f"(side {patch.side} {AXES[axis]}); {hint}move the patch region onto the geometry")
            face_slab = t[tuple(slab)]
            taken = selected & (face_slab != int(gas_kernels.FACE_WALL))
            if taken.any():
                raise ConfigError(f"patch {patch.name!r} overlaps another patch; make the patch regions disjoint")
            code = int(gas_kernels.FACE_INLET if patch.kind == "inlet" else gas_kernels.FACE_OUTLET)
            face_slab[selected] = code
            t[tuple(slab)] = face_slab
            vel_slab = vel[tuple(slab)]
            vel_slab[selected] = patch.velocity if patch.kind == "inlet" else (0.0, 0.0, 0.0)
            vel[tuple(slab)] = vel_slab
            p_slab = pres[tuple(slab)]
            p_slab[selected] = patch.pressure
            pres[tuple(slab)] = p_slab
            mask = np.zeros(t.shape, dtype=bool)
            mask_slab = mask[tuple(slab)]
            mask_slab[selected] = True
            mask[tuple(slab)] = mask_slab
            patch_faces[patch.name] = (axis, mask)

        face_type = gas_kernels.FaceInt()
        face_type.x, face_type.y, face_type.z = (wp.array(t, dtype=wp.int32, device=device) for t in types)
        face_bc = gas_kernels.FaceBc()
        face_bc.velocity_x, face_bc.velocity_y, face_bc.velocity_z = (
            wp.array(v, dtype=wp.vec3, device=device) for v in bc_vel)
        pressure = gas_kernels.FaceFloat()
        pressure.x, pressure.y, pressure.z = (wp.array(p, dtype=float, device=device) for p in bc_p)
        face_bc.pressure = pressure
        return FlowDomain(grid=grid, geometry=self, cell_fluid=cell_fluid, face_type=face_type,
                          face_bc=face_bc, patch_faces=patch_faces)
