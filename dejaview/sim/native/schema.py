"""The one description of what the native engine reads: the World's arrays, the static shapes'
parameters, the scalars, a body's state row and the model's constants and epsilons, by name.

``dejaview.sim.native`` packs a ``World`` from these tables (``pack``) and the C++ side reads them
through ``schema.h``, which ``header()`` generates from the same tables (committed beside
``rollout.cpp``; ``tests/sim/test_native_schema.py`` fails when the two differ). So the C++
names every field (``dv::schema::MASS``, ``dv::schema::SHAPE_RADIUS``,
``dv::schema::STATE_ORIENTATION``, ...) instead of counting positions, and ``dv::check_world`` checks each array's dtype and shape against this description,
naming the field in its error. Regenerate the header after editing this file::

    python -c "from dejaview.sim.native.schema import header; print(header(), end='')" \
        > dejaview/sim/native/schema.h

Adding a static shape kind or a contact parameter: ``docs/engines.md``, "Adding a shape kind or
a contact parameter".
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from dejaview.sim import box_edges, contacts, epsilons, line_contact, restitution
from dejaview.sim.state import STATE_LAYOUT, STATE_WIDTH, state_offsets
from dejaview.sim.world import STATIC_KINDS


@dataclass(frozen=True)
class Field:
    """One array the engine reads.

    Attributes:
        name: the World attribute it comes from (or what ``pack`` computes).
        dtype: ``"float64"`` or ``"int64"``.
        shape: dimension names (``N`` bodies, ``S`` spheres per body, ``K`` statics, ``P`` body
            pairs, ``G`` grid values of all grid statics, ``F`` the shape row) or sizes.
        doc: units and meaning.
    """

    name: str
    dtype: str
    shape: tuple
    doc: str


WORLD_FIELDS = (
    Field("mass", "float64", ("N",), "kg"),
    Field("inertia", "float64", ("N", 3, 3), "body-frame inertia about the centre of mass, kg m^2"),
    Field("inv_inertia", "float64", ("N", 3, 3), "its inverse"),
    Field("centers", "float64", ("N", "S", 3), "sphere centres relative to the centre of mass, body axes, m"),
    Field("radii", "float64", ("N", "S"), "sphere radii, m (0 for padding)"),
    Field("bound", "float64", ("N",), "radius about the centre of mass holding all spheres (a box: its corners), m"),
    Field("inv_inertia_min", "float64", ("N",), "1 / smallest principal moment"),
    Field("counts", "int64", ("N",), "real spheres per body (the first ones of its row)"),
    Field("mu_static", "float64", ("N", "K"), "friction coefficient body vs static"),
    Field("unload_static", "float64", ("N", "K"), "unloading stiffness factor body vs static (restitution)"),
    Field("pairs", "int64", ("P", 2), "movable body pairs checked for contact"),
    Field("mu_pair", "float64", ("P",), "friction coefficient per pair"),
    Field("unload_pair", "float64", ("P",), "unloading factor per pair"),
    Field("mass_pair", "float64", ("P",), "reduced mass per pair, kg"),
    Field("box_half", "float64", ("N", 3), "half extents of a box body, m (0: not a box)"),
    Field("pair_surface", "int64", ("P",), "which body's box surface the other's spheres meet: 0 a, 1 b, -1 none"),
    Field("shapes", "float64", ("K", "F"), "one row of SHAPE_COLUMNS per static shape"),
    Field("grid", "float64", ("G",), "the sampled distances of every grid static, one after another"),
    Field("paths", "float64", ("Q",), "the PATH_COLUMNS rows of every moving static, one after another"),
)
"""The World's arrays, in the order they travel (``pack``; ``dv::schema::WorldField``)."""

SHAPE_COLUMNS = (
    ("kind", 1, "index in KINDS"),
    ("rotation", 9, "world-from-shape rotation, row-major"),
    ("translation", 3, "shape origin in the world, m"),
    ("half", 3, "box half extents, m"),
    ("radius", 1, "sphere or cylinder radius, m"),
    ("half_height", 1, "cylinder half height, m"),
    ("grid_origin", 3, "grid: position of its first sample, shape frame, m"),
    ("grid_spacing", 1, "grid: sample spacing, m"),
    ("lipschitz", 1, "bound on |grad distance| (1 for analytic shapes)"),
    ("grid_shape", 3, "grid: samples per axis"),
    ("grid_offset", 1, "grid: index of its first value in the grid array"),
    ("path_offset", 1, "a moving static (a moving robot's link): index of its first path row's first "
                       "number in the paths array; -1 for a static that stands"),
    ("path_length", 1, "a moving static: its path's rows, one per substep time j h (held after the last)"),
)
"""One static shape's parameters: (name, width, meaning), in row order."""

PATH_COLUMNS = (
    ("rotation", 9, "world-from-shape rotation at substep time j h, row-major"),
    ("translation", 3, "shape origin in the world then, m"),
    ("velocity", 3, "velocity of the shape's origin then, m/s"),
    ("angular_velocity", 3, "the shape's angular velocity then, rad/s"),
)
"""One row of a moving static's path (``dejaview.sim.motion.ShapePath``): (name, width, meaning)."""

PATH_WIDTH = sum(width for _, width, _ in PATH_COLUMNS)

KINDS = {kind: code for code, kind in enumerate(STATIC_KINDS)}
"""Static shape kind -> the code in the shape row's ``kind`` column."""

FLOATS = ("gravity_x", "gravity_y", "gravity_z", "substep_dt", "contact_frequency", "unload_velocity")
"""Scalars (s, rad/s, m/s); the rollout may append its divergence limits (reach, speed)."""

INTS = ("substeps", "max_static_contacts", "max_pair_contacts", "first_substep")
"""Integer settings (``first_substep``: the substep number the rollout starts at, where moving statics
stand; 0 in ``pack``, a rollout continued from step i passes ``i * substeps``)."""

CONSTANTS = {
    "SLIP_EPS": (contacts.SLIP_EPS, "m/s: friction direction regulariser (dejaview.sim.contacts)"),
    "SMOOTH_MIN_POWER": (contacts.SMOOTH_MIN_POWER, "power of the friction's smooth minimum"),
    "UNLOAD_WIDTH": (restitution.UNLOAD_WIDTH, "w: an impact's loading-to-unloading blend spans about 4 w rad "
                                            "of its phase (restitution.loading)"),
    "UNLOAD_LEAD": (restitution.UNLOAD_LEAD, "beta: the blend is centred beta w rad before an impact's deepest "
                                          "point (restitution.loading)"),
    "UNLOAD_MIN": (restitution.UNLOAD_MIN, "the least unloading factor phi; the physics' factor acts on "
                                        "phi - UNLOAD_MIN (restitution.UNLOAD_MIN)"),
    "LINE_ASPECT": (line_contact.LINE_ASPECT, "a static contact set whose in-plane second moments' ratio "
                                          "exceeds this is a line: its roll is held (line_roll_stick)"),
    "ROLL_STOP_OMEGA_T": (line_contact.ROLL_STOP_OMEGA_T, "omega_0 times the time in which the roll stick "
                                                          "stops a line's roll, at least one substep"),
    "LINE_MIN_SPREAD": (line_contact.LINE_MIN_SPREAD, "m^2: a static contact set whose in-plane second "
                                                      "moment is at most this is a point, not a line"),
    "EDGE_SPACING": (box_edges.EDGE_SPACING, "m: spacing of the points along a static box's edges that "
                                            "meet a box body's exact faces (static_edge_points)"),
    "BOX_CORNER_RADIUS": (box_edges.BOX_CORNER_RADIUS, "m: radius of the spheres at a box body's corners, "
                                                      "which meet planes and static boxes (box_corners)"),
    "CLEAR_MARGIN": (1e-9, "m: a sphere or pair whose clearance bound stays above this cannot touch "
                           "and is skipped (native culling only)"),
}
"""Model constants the C++ reads from ``schema.h`` (the torch engine reads the same names)."""

EPSILONS = {
    "TINY": (epsilons.TINY, "guard under a square root or in a denominator that may be 0"),
    "NORMAL_EPS2": (epsilons.NORMAL_EPS2, "m^2: added to a squared length under its root when "
                                          "normalising (no direction below ~1e-12 m)"),
    "GRID_OUTSIDE": (epsilons.GRID_OUTSIDE, "m: beyond this outside a grid's box, the box's direction "
                                            "is the normal"),
    "SMALL_ANGLE_F64": (epsilons.SMALL_ANGLE_F64, "rad: rotvec_to_quat's series below this (double)"),
    "SMALL_ANGLE_F32": (epsilons.SMALL_ANGLE_F32, "rad: ... (float)"),
    "SLAB_PARALLEL": (1e-12, "a static box edge's direction component below this is parallel to the "
                             "body box's slab (native edge selection only)"),
}
"""The numerical guards of ``dejaview.sim.epsilons`` the C++ reads from ``schema.h``."""

STATE = STATE_LAYOUT
"""One body's state row (``dejaview.sim.state.STATE_LAYOUT``): (name, width, meaning); the native
engine's states are (B, N, STATE_WIDTH) arrays of these rows."""


def shape_offsets() -> dict[str, tuple[int, int]]:
    """Column name -> (first index, width) in a shape row."""
    out, at = {}, 0
    for name, width, _ in SHAPE_COLUMNS:
        out[name] = (at, width)
        at += width
    return out


SHAPE_WIDTH = sum(width for _, width, _ in SHAPE_COLUMNS)
"""Numbers per shape row (``F``)."""


def grid_lipschitz(values: torch.Tensor, spacing: float) -> float:
    """Lipschitz bound of ``dejaview.sim.sdf.sdf_grid`` over all space.

    Inside a cell the trilinear interpolant's derivative along an axis is a
    blend of the differences along the cell's four edges of that axis, so its
    gradient norm is at most ``sqrt(sum_axes max_edges diff^2) / spacing``;
    ``L_g`` is the largest over the cells. Outside the grid the field is the
    value at the clamped point plus the distance to the grid box: clamp and
    remainder split every coordinate change between them, which bounds the
    whole field by ``sqrt(2) max(L_g, 1)``.
    """
    if min(values.shape) < 2:
        return float("inf")
    edge = []
    for axis in range(3):
        d = values.diff(dim=axis).abs()
        for a in (a for a in range(3) if a != axis):  # max over the cell's 4 edges along ``axis``
            d = torch.maximum(d.narrow(a, 0, d.shape[a] - 1), d.narrow(a, 1, d.shape[a] - 1))
        edge.append(d)  # (nx - 1, ny - 1, nz - 1): one number per cell
    sq = edge[0] ** 2 + edge[1] ** 2 + edge[2] ** 2
    lg = float(sq.max().sqrt()) / spacing
    return 2.0 ** 0.5 * max(lg, 1.0)


def pack(world) -> tuple[list[torch.Tensor], list[float], list[int]]:
    """The World as the named arrays and scalars of this schema, in schema order.

    Returns:
        tensors (``WORLD_FIELDS`` order, contiguous), floats (``FLOATS``), ints (``INTS``).
    """
    f64 = dict(dtype=torch.float64)
    cols = shape_offsets()
    shapes = torch.zeros(len(world.statics), SHAPE_WIDTH, **f64)
    grids, offset = [], 0
    paths, path_at = [], 0
    for k, s in enumerate(world.statics):
        values = {"kind": KINDS[s.kind], "rotation": s.rotation.reshape(9), "translation": s.translation,
                  "half": s.half, "radius": s.radius, "half_height": s.half_height,
                  "grid_origin": s.grid_origin, "grid_spacing": s.grid_spacing, "lipschitz": 1.0,
                  "path_offset": -1.0, "path_length": 0.0}
        if s.path is not None:
            rows = s.path.rows().to(torch.float64)  # (T, PATH_WIDTH)
            values.update(path_offset=float(path_at), path_length=float(rows.shape[0]))
            paths.append(rows.reshape(-1))
            path_at += rows.numel()
        if s.kind == "grid":
            values.update(lipschitz=grid_lipschitz(s.grid, s.grid_spacing),
                          grid_shape=torch.tensor(s.grid.shape, **f64), grid_offset=offset)
            grids.append(s.grid.reshape(-1))
            offset += s.grid.numel()
        for name, value in values.items():
            first, width = cols[name]
            shapes[k, first:first + width] = torch.as_tensor(value, **f64).reshape(width)
    k = len(world.statics)
    arrays = {
        "mass": world.mass, "inertia": world.inertia, "inv_inertia": world.inv_inertia,
        "centers": world.centers, "radii": world.radii, "bound": world.bound,
        "inv_inertia_min": world.inv_inertia_min, "counts": world.mask.sum(-1).round().to(torch.int64),
        "mu_static": world.mu_static.reshape(world.num_bodies, k),
        "unload_static": world.unload_static.reshape(world.num_bodies, k),
        "pairs": world.pairs.reshape(-1, 2), "mu_pair": world.mu_pair, "unload_pair": world.unload_pair,
        "mass_pair": world.mass_pair, "box_half": world.box_half,
        "pair_surface": torch.tensor(world.pair_surface, dtype=torch.int64).reshape(-1), "shapes": shapes,
        "grid": torch.cat(grids) if grids else torch.zeros(0, **f64),
        "paths": torch.cat(paths) if paths else torch.zeros(0, **f64),
    }
    tensors = [arrays[f.name].contiguous() for f in WORLD_FIELDS]
    scalars = {"gravity_x": world.gravity[0], "gravity_y": world.gravity[1], "gravity_z": world.gravity[2],
               "substep_dt": world.dt / world.substeps, "contact_frequency": world.contact.frequency,
               "unload_velocity": world.contact.unload_velocity}
    integers = {"substeps": world.substeps, "max_static_contacts": world.contact.max_static_contacts,
                "max_pair_contacts": world.contact.max_pair_contacts, "first_substep": 0}
    return tensors, [float(scalars[n]) for n in FLOATS], [int(integers[n]) for n in INTS]


def _cpp_name(name: str) -> str:
    return name.upper()


def header() -> str:
    """``schema.h``: this module's tables as C++ names (generated; do not edit by hand)."""
    dims = {"N": 0, "S": 1, "K": 2, "P": 3, "G": 4, "F": 5, "Q": 6}
    lines = ["// Generated by dejaview.sim.native.schema.header() from dejaview/sim/native/schema.py:",
             "// edit that file and regenerate (its docstring says how), not this one.",
             "#pragma once", "#include <cstdint>", "", "namespace dv {", "namespace schema {", ""]
    lines.append("// the World's arrays, in the order they travel (WORLD_FIELDS)")
    lines.append("enum WorldField : int {")
    lines += [f"  {_cpp_name(f.name)} = {i},  // {f.dtype} ({', '.join(map(str, f.shape))}): {f.doc}"
              for i, f in enumerate(WORLD_FIELDS)]
    lines += [f"  WORLD_FIELD_COUNT = {len(WORLD_FIELDS)}", "};", ""]
    lines.append("// symbolic dimensions of the arrays' shapes")
    lines.append("enum Dim : int { " + ", ".join(f"DIM_{d} = {-(i + 1)}" for d, i in dims.items()) + " };")
    lines.append("struct FieldSpec { const char* name; bool is_int; int ndim; int dims[3]; };")
    lines.append("constexpr FieldSpec WORLD_SPECS[WORLD_FIELD_COUNT] = {")
    for f in WORLD_FIELDS:
        d = [str(x) if isinstance(x, int) else f"DIM_{x}" for x in f.shape] + ["0"] * (3 - len(f.shape))
        lines.append(f'  {{"{f.name}", {"true" if f.dtype == "int64" else "false"}, {len(f.shape)}, '
                     f'{{{", ".join(d)}}}}},')
    lines += ["};", ""]
    lines.append("// one static shape's row (SHAPE_COLUMNS): first index of each column")
    for name, (first, width) in shape_offsets().items():
        lines.append(f"constexpr int SHAPE_{_cpp_name(name)} = {first};  // {width} number(s)")
    lines += [f"constexpr int SHAPE_WIDTH = {SHAPE_WIDTH};", ""]
    lines.append("// one row of a moving static's path (PATH_COLUMNS): first index of each column")
    at = 0
    for name, width, _ in PATH_COLUMNS:
        lines.append(f"constexpr int PATH_{_cpp_name(name)} = {at};  // {width} number(s)")
        at += width
    lines += [f"constexpr int PATH_WIDTH = {PATH_WIDTH};", ""]
    lines.append("// static shape kinds (KINDS)")
    lines += [f"constexpr int KIND_{_cpp_name(kind)} = {code};" for kind, code in KINDS.items()]
    lines += [f"constexpr int KIND_COUNT = {len(KINDS)};", ""]
    lines.append("// scalars (FLOATS) and integer settings (INTS): their positions")
    lines += [f"constexpr int F_{_cpp_name(n)} = {i};" for i, n in enumerate(FLOATS)]
    lines += [f"constexpr int FLOAT_COUNT = {len(FLOATS)};"]
    lines += [f"constexpr int I_{_cpp_name(n)} = {i};" for i, n in enumerate(INTS)]
    lines += [f"constexpr int INT_COUNT = {len(INTS)};", ""]
    lines.append("// one body's state row (STATE): first index of each part")
    for name, (first, width) in state_offsets().items():
        lines.append(f"constexpr int STATE_{_cpp_name(name)} = {first};  // {width} number(s)")
    lines += [f"constexpr int STATE_WIDTH = {STATE_WIDTH};", ""]
    lines.append("// model constants (CONSTANTS)")
    lines += [f"constexpr double {name} = {value!r};  // {doc}" for name, (value, doc) in CONSTANTS.items()]
    lines += ["", "// numerical guards (EPSILONS)"]
    lines += [f"constexpr double {name} = {value!r};  // {doc}" for name, (value, doc) in EPSILONS.items()]
    lines += ["", "}  // namespace schema", "}  // namespace dv", ""]
    return "\n".join(lines)
