"""Posterior samples for analysis tools: named numpy arrays, a pandas DataFrame of ``posterior.csv``
and an ArviZ ``InferenceData`` (``posterior.nc``) whose chains are the sampler's independent runs.

pandas and arviz come with the ``analysis`` extra; they are imported here, on first use, and
nothing else in DejaView needs them (``write_netcdf`` writes nothing without arviz).

ArviZ variables (physical units, the free parameters only, as ``result.json``'s intervals name
them: ``ParameterLayout.names``): ``position`` (m, object-frame origin; dim ``position_axis``, the
free axes among x y z), ``orientation`` (rad, rotation vector on top of the ``<pose>``
orientation; dim ``rotation_axis``: rx ry rz), ``linear_velocity`` (m/s) and ``angular_velocity``
(rad/s) (dim ``velocity_axis``: x y z) and, where inferred, ``friction``, ``restitution``,
``stiffness`` (scalars).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import torch

from dejaview.inference.posterior_report import CSV_HEADER, PHYSICS_COLUMNS, chain_rows, physical, state_rows

DIMS = {"position": "position_axis", "orientation": "rotation_axis", "linear_velocity": "velocity_axis",
        "angular_velocity": "velocity_axis"}
"""The ArviZ dimension of each vector variable (physics parameters are scalars)."""
UNITS = {"position": "m", "orientation": "rad", "linear_velocity": "m/s", "angular_velocity": "rad/s",
         "stiffness": "N/m/kg"}
"""Each variable's ``units`` attribute (friction and restitution: 1)."""


def parameter_arrays(samples, layout) -> dict[str, np.ndarray]:
    """The samples as numpy arrays: each free parameter (N,) in physical units under its
    ``layout.names()`` name (``position.x``, ``orientation.rx``, ``physics.friction``...), then
    ``weight`` (N,), ``run`` (N,) (which independent run drew it; 0 for one run) and
    ``log_density`` (N,) (the unnormalised log posterior density, ``reference.log_density``)."""
    values = physical(layout, samples.x).numpy()
    out = {name: values[:, j].copy() for j, name in enumerate(layout.names())}
    out["weight"] = samples.weights.to(torch.float64).numpy().copy()
    out["run"] = _runs(samples)
    out["log_density"] = samples.log_density.to(torch.float64).numpy().copy()
    return out


def csv_columns(samples, layout) -> dict[str, np.ndarray]:
    """``posterior.csv``'s columns (``CSV_HEADER``, then ``PHYSICS_COLUMNS`` where physics was
    inferred) as numpy arrays (N,), the same numbers ``write_csv`` writes."""
    parts = [state_rows(layout, samples.x)]
    header = CSV_HEADER
    if layout.physics is not None:
        with torch.no_grad():
            parts.append(layout.physics_values(samples.x.to(torch.float64)))
        header = CSV_HEADER + PHYSICS_COLUMNS
    rows = torch.cat(parts, -1).to(torch.float64).numpy()
    n = rows.shape[0]
    out = {"sample": np.arange(n), "weight": samples.weights.to(torch.float64).numpy().copy()}
    out.update({name: rows[:, j].copy() for j, name in enumerate(header[2:])})
    return out


def frame(samples, layout):
    """``posterior.csv`` as a pandas DataFrame: its columns, in its order, with its values.

    Raises:
        ImportError: pandas is not installed (``pip install 'dejaview[analysis]'``).
    """
    pd = _require("pandas")
    return pd.DataFrame(csv_columns(samples, layout))


def chains(samples) -> list[np.ndarray]:
    """Row indices of each chain: each independent run's samples in their order, cut to the
    smallest run's size (``posterior_report.chain_rows``; one chain where there was one run)."""
    return [r.numpy() for r in chain_rows(torch.as_tensor(_runs(samples)))]


def to_inference_data(samples, layout, attrs: dict | None = None):
    """The samples as an ``arviz.InferenceData``.

    Groups: ``posterior`` (chain, draw, ...): the variables of the module docstring, one chain per
    independent run of the sampler (``chains``), so ArviZ's diagnostics compare the runs, as
    DejaView's R-hat does (its ESS is ArviZ's; its R-hat is not split: docs/inference.md,
    "Notebooks and ArviZ"); ``sample_stats`` (chain, draw): ``lp`` (the unnormalised log posterior density) and,
    where the weights are not all equal, ``weight`` (ArviZ's own statistics and plots do not use
    it).

    Args:
        samples: ``PosteriorSamples``; layout: its ``ParameterLayout``; attrs: extra attributes
            (strings and numbers) of the groups.
    Raises:
        ImportError: arviz is not installed (``pip install 'dejaview[analysis]'``).
    """
    az = _require("arviz")
    rows = chains(samples)
    values = physical(layout, samples.x).numpy()
    posterior, coords, dims = {}, {}, {}
    for block, columns in _blocks(layout.names()).items():
        if block == "physics":
            for comp, j in columns:
                posterior[comp] = np.stack([values[r, j] for r in rows])
            continue
        dim = DIMS[block]
        coords[dim] = [comp for comp, _ in columns]
        dims[block] = [dim]
        posterior[block] = np.stack([values[r][:, [j for _, j in columns]] for r in rows])
    stats = {"lp": np.stack([samples.log_density.to(torch.float64).numpy()[r] for r in rows])}
    w = samples.weights.to(torch.float64).numpy()
    if not np.allclose(w, w[0], rtol=1e-12, atol=0.0):
        stats["weight"] = np.stack([w[r] for r in rows])
    group_attrs = {"inference_library": "dejaview", **(attrs or {})}
    data = az.from_dict(posterior=posterior, sample_stats=stats, coords=coords, dims=dims,
                        posterior_attrs=group_attrs, sample_stats_attrs=group_attrs)
    for name, var in data.posterior.data_vars.items():
        var.attrs["units"] = UNITS.get(name, "1")
    return data


def variable_of(name: str) -> tuple[str, dict]:
    """Where ``result.json``'s parameter ``name`` lives in ``to_inference_data``'s posterior: the
    variable and the selection, e.g. ``("orientation", {"rotation_axis": "rx"})`` for
    ``orientation.rx``, ``("friction", {})`` for ``physics.friction``."""
    block, comp = name.split(".", 1)
    return (comp, {}) if block == "physics" else (block, {DIMS[block]: comp})


def write_netcdf(path, samples, layout, attrs: dict | None = None) -> Path | None:
    """``posterior.nc``: ``to_inference_data`` written by ArviZ (netCDF4 format through h5netcdf).
    None, and nothing written, where arviz is not installed."""
    try:
        _require("arviz")
    except ImportError:
        return None
    to_inference_data(samples, layout, attrs).to_netcdf(str(path))
    return Path(path)


def _blocks(names: list[str]) -> dict[str, list[tuple[str, int]]]:
    """``layout.names()`` grouped by block: block -> [(component, column)] in column order."""
    out: dict[str, list[tuple[str, int]]] = {}
    for j, name in enumerate(names):
        block, comp = name.split(".", 1)
        out.setdefault(block, []).append((comp, j))
    return out


def _runs(samples) -> np.ndarray:
    n = samples.x.shape[0]
    return np.zeros(n, dtype=np.int64) if samples.run is None else samples.run.numpy().astype(np.int64)


def _require(module: str):
    """Import an ``analysis`` extra's module (arviz warns on import of its coming refactor: not
    the user's concern here)."""
    import importlib

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)
            return importlib.import_module(module)
    except ImportError as e:
        raise ImportError(f"{module} is needed for this (pip install 'dejaview[analysis]'): {e}") from e
