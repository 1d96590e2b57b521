// The World's arrays as rollout.cpp receives them (dejaview/sim/native/schema.py's pack), checked
// against schema.h (check_world) and read into a World (make_world) (dejaview.sim.native).
#pragma once

#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

#include "contacts.h"
#include "schema.h"

namespace dv {

// Checks the World's arrays against schema.h (count, dtype, rank, sizes; the symbolic sizes N, S,
// K, P, G must agree across arrays), naming the field of the first mismatch.
inline void check_world(const std::vector<torch::Tensor>& t, const std::vector<double>& f,
                        const std::vector<int64_t>& iv, bool limits_allowed) {
  using namespace schema;
  TORCH_CHECK(static_cast<int>(t.size()) == WORLD_FIELD_COUNT, "native world: ", t.size(), " arrays, the schema has ",
              static_cast<int>(WORLD_FIELD_COUNT), " (dejaview/sim/native/schema.py and schema.h out of step?)");
  TORCH_CHECK(f.size() == FLOAT_COUNT || (limits_allowed && f.size() == FLOAT_COUNT + 2), "native world: ",
              f.size(), " floats, the schema has ", FLOAT_COUNT, limits_allowed ? " (+2 divergence limits)" : "");
  TORCH_CHECK(iv.size() == INT_COUNT, "native world: ", iv.size(), " ints, the schema has ", INT_COUNT);
  int64_t sizes[7] = {-1, -1, -1, -1, -1, SHAPE_WIDTH, -1};  // N, S, K, P, G, F, Q
  for (int i = 0; i < WORLD_FIELD_COUNT; ++i) {
    const FieldSpec& spec = WORLD_SPECS[i];
    const torch::Tensor& x = t[i];
    TORCH_CHECK(x.device().is_cpu() && x.scalar_type() == (spec.is_int ? torch::kInt64 : torch::kFloat64),
                "native world field '", spec.name, "': expected ", spec.is_int ? "int64" : "float64",
                " on the CPU, got ", x.scalar_type(), " on ", x.device());
    TORCH_CHECK(x.dim() == spec.ndim, "native world field '", spec.name, "': expected ", spec.ndim,
                " dimensions, got shape ", x.sizes());
    for (int d = 0; d < spec.ndim; ++d) {
      const int want = spec.dims[d];  // a size, or -1 - the index of a named dimension
      if (want < 0 && sizes[-want - 1] < 0) {  // the first array to name it sets it
        sizes[-want - 1] = x.size(d);
        continue;
      }
      const int64_t expected = want < 0 ? sizes[-want - 1] : want;
      TORCH_CHECK(x.size(d) == expected, "native world field '", spec.name, "': dimension ", d, " is ",
                  x.size(d), ", expected ", expected, " (shape ", x.sizes(), ")");
    }
  }
  TORCH_CHECK(iv[I_SUBSTEPS] >= 1 && iv[I_MAX_STATIC_CONTACTS] >= 1 && iv[I_MAX_PAIR_CONTACTS] >= 1,
              "native world: substeps and contact capacities must be >= 1");
  TORCH_CHECK(iv[I_FIRST_SUBSTEP] >= 0, "native world: first_substep must be >= 0");
}

template <typename S>
World<S> make_world(const std::vector<torch::Tensor>& t, const std::vector<double>& f, const std::vector<int64_t>& iv) {
  using namespace schema;  // the arrays, the shape row's columns, the scalars: schema.h
  World<S> w;
  w.n = static_cast<int>(t[MASS].size(0));
  w.s_max = static_cast<int>(t[CENTERS].size(1));
  w.k = static_cast<int>(t[SHAPES].size(0));
  w.p = static_cast<int>(t[PAIRS].size(0));
  w.mass = t[MASS].data_ptr<S>();
  w.inertia = t[INERTIA].data_ptr<S>();
  w.inv_inertia = t[INV_INERTIA].data_ptr<S>();
  w.centers = t[CENTERS].data_ptr<S>();
  w.radii = t[RADII].data_ptr<S>();
  w.bound = t[BOUND].data_ptr<S>();
  w.inv_i_min = t[INV_INERTIA_MIN].data_ptr<S>();
  const int64_t* counts = t[COUNTS].data_ptr<int64_t>();
  for (int i = 0; i < w.n; ++i) {
    TORCH_CHECK(counts[i] >= 0 && counts[i] <= w.s_max, "native world field 'counts': body ", i, " has ",
                counts[i], " spheres of at most ", w.s_max);
    w.count.push_back(static_cast<int>(counts[i]));
    S reach = 0;
    for (int j = 0; j < w.count[i]; ++j) {
      const S* c = w.centers + (static_cast<int64_t>(i) * w.s_max + j) * 3;
      reach = std::max(reach, std::sqrt(c[0] * c[0] + c[1] * c[1] + c[2] * c[2]));
    }
    w.reach.push_back(reach);
  }
  w.mu_static = t[MU_STATIC].data_ptr<S>();
  w.unload_static = t[UNLOAD_STATIC].data_ptr<S>();
  w.pairs = t[PAIRS].data_ptr<int64_t>();
  w.mu_pair = t[MU_PAIR].data_ptr<S>();
  w.unload_pair = t[UNLOAD_PAIR].data_ptr<S>();
  w.mass_pair = t[MASS_PAIR].data_ptr<S>();
  w.box_half = t[BOX_HALF].data_ptr<S>();
  w.pair_surface = t[PAIR_SURFACE].data_ptr<int64_t>();
  for (int pi = 0; pi < w.p; ++pi)
    TORCH_CHECK(w.pair_surface[pi] >= -1 && w.pair_surface[pi] <= 1, "native world field 'pair_surface': pair ",
                pi, " has ", w.pair_surface[pi], " (schema: -1, 0 or 1)");
  for (int i = 0; i < w.n; ++i) {  // a box's surface and corner spheres reach its corners, beyond its spheres' centres
    const S* half = w.box_half + 3 * i;
    w.reach[i] = std::max(w.reach[i], std::sqrt(half[0] * half[0] + half[1] * half[1] + half[2] * half[2]));
  }
  const S* rows = t[SHAPES].data_ptr<S>();
  const S* grid = t[GRID].numel() ? t[GRID].data_ptr<S>() : nullptr;
  const int64_t grid_size = t[GRID].numel();
  for (int k = 0; k < w.k; ++k) {
    const S* r = rows + static_cast<int64_t>(SHAPE_WIDTH) * k;
    Shape<S> sh;
    sh.kind = static_cast<int>(r[SHAPE_KIND]);
    TORCH_CHECK(sh.kind >= 0 && sh.kind < KIND_COUNT, "native world field 'shapes': static ", k, " has kind ",
                r[SHAPE_KIND], " (schema: 0 to ", KIND_COUNT - 1, ")");
    for (int i = 0; i < 9; ++i) sh.rot[i] = r[SHAPE_ROTATION + i];
    for (int i = 0; i < 3; ++i) {
      sh.trans[i] = r[SHAPE_TRANSLATION + i];
      sh.half[i] = r[SHAPE_HALF + i];
      sh.origin[i] = r[SHAPE_GRID_ORIGIN + i];
    }
    sh.radius = r[SHAPE_RADIUS];
    sh.half_height = r[SHAPE_HALF_HEIGHT];
    sh.spacing = r[SHAPE_GRID_SPACING];
    sh.lipschitz = r[SHAPE_LIPSCHITZ];
    sh.nx = static_cast<int64_t>(r[SHAPE_GRID_SHAPE]);
    sh.ny = static_cast<int64_t>(r[SHAPE_GRID_SHAPE + 1]);
    sh.nz = static_cast<int64_t>(r[SHAPE_GRID_SHAPE + 2]);
    const int64_t offset = static_cast<int64_t>(r[SHAPE_GRID_OFFSET]);
    if (sh.kind == KIND_GRID)
      TORCH_CHECK(offset >= 0 && offset + sh.nx * sh.ny * sh.nz <= grid_size, "native world field 'grid': static ",
                  k, "'s samples run past its end");
    sh.grid = sh.kind == KIND_GRID ? grid + offset : nullptr;
    const int64_t path_at = static_cast<int64_t>(r[SHAPE_PATH_OFFSET]);
    sh.path_len = static_cast<int64_t>(r[SHAPE_PATH_LENGTH]);
    if (path_at >= 0) {
      TORCH_CHECK(sh.path_len >= 1 && path_at + sh.path_len * PATH_WIDTH <= t[PATHS].numel(),
                  "native world field 'paths': static ", k, "'s path runs past its end");
      sh.path = t[PATHS].data_ptr<S>() + path_at;
      w.moving = true;
    }
    w.shapes.push_back(sh);
  }
  w.gravity[0] = static_cast<S>(f[F_GRAVITY_X]);
  w.gravity[1] = static_cast<S>(f[F_GRAVITY_Y]);
  w.gravity[2] = static_cast<S>(f[F_GRAVITY_Z]);
  w.h = static_cast<S>(f[F_SUBSTEP_DT]);
  w.omega = static_cast<S>(f[F_CONTACT_FREQUENCY]);
  w.unload_velocity = static_cast<S>(f[F_UNLOAD_VELOCITY]);
  w.substeps = static_cast<int>(iv[I_SUBSTEPS]);
  w.cap_static = static_cast<int>(iv[I_MAX_STATIC_CONTACTS]);
  w.cap_pair = static_cast<int>(iv[I_MAX_PAIR_CONTACTS]);
  w.first_substep = iv[I_FIRST_SUBSTEP];
  if (w.moving) pose_shapes(w, 0);
  return w;
}

}  // namespace dv
