"""Meshes shared by the geometry tests (built in memory, metres)."""

from __future__ import annotations

import pytest
import trimesh


def make_table() -> trimesh.Trimesh:
    """A 1.2 x 0.8 x 0.75 m table: a 4 cm top on four 5 cm legs, standing on z = 0."""
    top = trimesh.creation.box(extents=(1.2, 0.8, 0.04))
    top.apply_translation((0.0, 0.0, 0.73))
    parts = [top]
    for sx in (-1, 1):
        for sy in (-1, 1):
            leg = trimesh.creation.box(extents=(0.05, 0.05, 0.71))
            leg.apply_translation((sx * 0.55, sy * 0.35, 0.355))
            parts.append(leg)
    return trimesh.boolean.union(parts, engine="manifold")


@pytest.fixture(scope="session")
def box_mesh() -> trimesh.Trimesh:
    return trimesh.creation.box(extents=(0.2, 0.15, 0.1))


@pytest.fixture(scope="session")
def ball_mesh() -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=3, radius=0.05)


@pytest.fixture(scope="session")
def table_mesh() -> trimesh.Trimesh:
    return make_table()
