// Fused multi-resolution hash encoding on CPU (forward, backward to tables, backward to points).
//
// A torch C++ extension registered as the operator namespace `hypnerf_hashgrid`, parallelised
// with OpenMP (the same libgomp torch itself uses, so torch.set_num_threads applies). Semantics
// match the pure-PyTorch reference in model/encoding.py exactly:
//   - coordinates are clamped into [0, 1] (NaN -> 0); the point gradient is zero outside [0, 1];
//   - level resolution `res` has res + 1 vertices per axis; cell = min(floor(x * res), res - 1),
//     so x = 1 lands in the last cell with fraction 1 and no corner leaves the grid;
//   - dense levels index x + y (res + 1) + z (res + 1)^2, hashed levels
//     (x * 1 ^ y * 2654435761 ^ z * 805459861) mod T.
// Hash products are formed in uint32: T is a power of two <= 2^24, so the low log2(T) bits of a
// product (and of an XOR of products) are the same whether it is taken mod 2^32 or in int64.
//
// Work is done in chunks of kChunk points, level by level, with the point loop written so the
// compiler vectorises it (gathers for the table reads); the chunk's scratch lives on the stack,
// so steady-state calls touch no freshly allocated memory apart from the outputs.

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/zeros.h>
#include <omp.h>
#include <torch/library.h>

#include <algorithm>
#include <cstdint>
#include <vector>

namespace {

constexpr uint32_t kPrimeY = 2654435761u;
constexpr uint32_t kPrimeZ = 805459861u;
constexpr int kChunk = 128;

struct Level {
  uint32_t res;
  uint32_t stride_y;  // dense strides: res + 1 and (res + 1)^2
  uint32_t stride_z;
  bool dense;
};

std::vector<Level> make_levels(c10::IntArrayRef resolutions, c10::IntArrayRef dense) {
  std::vector<Level> levels;
  for (size_t l = 0; l < resolutions.size(); ++l) {
    const auto r = static_cast<uint32_t>(resolutions[l]);
    levels.push_back({r, r + 1, (r + 1) * (r + 1), dense[l] != 0});
  }
  return levels;
}

// Clamp into [0, 1]; the comparisons are false for NaN, which therefore maps to 0.
template <typename T>
inline T clamp01(T x) {
  return x >= T(0) ? (x <= T(1) ? x : T(1)) : T(0);
}

template <typename T>
inline T inside01(T x) {
  return (x >= T(0) && x <= T(1)) ? T(1) : T(0);
}

// Cell index and fraction of a clamped coordinate at a level with `res` cells per axis.
template <typename T>
inline void cell(T x, T resf, uint32_t last, uint32_t& i, T& f) {
  const T pos = x * resf;
  i = std::min(static_cast<uint32_t>(pos), last);  // pos >= 0: truncation is floor
  f = pos - static_cast<T>(i);
}

// Table row of corner c (bit 0: +x, bit 1: +y, bit 2: +z) of the cell at (ix, iy, iz).
template <bool Dense>
inline uint32_t corner(int c, uint32_t ix, uint32_t iy, uint32_t iz, const Level& lv, uint32_t mask) {
  const uint32_t x = ix + (c & 1), y = iy + ((c >> 1) & 1), z = iz + ((c >> 2) & 1);
  if constexpr (Dense) {
    return x + y * lv.stride_y + z * lv.stride_z;
  } else {
    return (x ^ (y * kPrimeY) ^ (z * kPrimeZ)) & mask;
  }
}

// Trilinear weight of corner c from the per-axis fractions.
template <typename T>
inline T weight(int c, T fx, T fy, T fz) {
  return ((c & 1) ? fx : T(1) - fx) * ((c & 2) ? fy : T(1) - fy) * ((c & 4) ? fz : T(1) - fz);
}

// Chunk-local copy of the points, clamped, in structure-of-arrays layout.
template <typename T>
struct ChunkPoints {
  alignas(64) T x[kChunk];
  alignas(64) T y[kChunk];
  alignas(64) T z[kChunk];

  void load(const T* pts, int n) {
    for (int p = 0; p < n; ++p) {
      x[p] = clamp01(pts[3 * p + 0]);
      y[p] = clamp01(pts[3 * p + 1]);
      z[p] = clamp01(pts[3 * p + 2]);
    }
  }
};

// Interpolated features of one level for a chunk, written to out[f * kChunk + p].
template <typename T, int F, bool Dense>
void forward_level(const ChunkPoints<T>& cp, int n, const T* __restrict tab, const Level& lv, uint32_t mask,
                   T* __restrict out) {
  const T resf = static_cast<T>(lv.res);
  const uint32_t last = lv.res - 1;
#pragma omp simd
  for (int p = 0; p < n; ++p) {
    uint32_t ix, iy, iz;
    T fx, fy, fz;
    cell(cp.x[p], resf, last, ix, fx);
    cell(cp.y[p], resf, last, iy, fy);
    cell(cp.z[p], resf, last, iz, fz);
    T acc[F] = {};
#pragma GCC unroll 8
    for (int c = 0; c < 8; ++c) {
      const T w = weight(c, fx, fy, fz);
      const T* row = tab + static_cast<size_t>(corner<Dense>(c, ix, iy, iz, lv, mask)) * F;
#pragma GCC unroll 8
      for (int f = 0; f < F; ++f) acc[f] += w * row[f];
    }
#pragma GCC unroll 8
    for (int f = 0; f < F; ++f) out[f * kChunk + p] = acc[f];
  }
}

template <typename T, int F>
void forward_impl(const T* points, const T* tables, T* out, int64_t batch, int64_t n, int64_t table_size,
                  const std::vector<Level>& levels) {
  const int L = static_cast<int>(levels.size());
  const int width = L * F;
  const auto mask = static_cast<uint32_t>(table_size - 1);
  const int64_t chunks_per_object = (n + kChunk - 1) / kChunk;
  const int64_t total = batch * chunks_per_object;
#pragma omp parallel num_threads(at::get_num_threads()) if (total > 1)
  {
    ChunkPoints<T> cp;
    std::vector<T> level_out(static_cast<size_t>(width) * kChunk);
#pragma omp for schedule(static)
    for (int64_t job = 0; job < total; ++job) {
      const int64_t b = job / chunks_per_object;
      const int64_t p0 = (job % chunks_per_object) * kChunk;
      const int cn = static_cast<int>(std::min<int64_t>(kChunk, n - p0));
      cp.load(points + (b * n + p0) * 3, cn);
      const T* obj_tables = tables + b * L * table_size * F;
      for (int l = 0; l < L; ++l) {
        const T* tab = obj_tables + l * table_size * F;
        T* dst = level_out.data() + static_cast<size_t>(l) * F * kChunk;
        if (levels[l].dense) {
          forward_level<T, F, true>(cp, cn, tab, levels[l], mask, dst);
        } else {
          forward_level<T, F, false>(cp, cn, tab, levels[l], mask, dst);
        }
      }
      // Transpose the chunk from [L*F][point] to the output's [point][L*F].
      T* o = out + (b * n + p0) * width;
      for (int p = 0; p < cn; ++p) {
        for (int j = 0; j < width; ++j) o[p * width + j] = level_out[static_cast<size_t>(j) * kChunk + p];
      }
    }
  }
}

// Gradients of one level for a chunk. `g` holds the upstream gradient as g[f * kChunk + p].
// Point gradients accumulate into gx/gy/gz; the table rows and weights of the 8 corners are
// left in rows/weights ([corner][point]) for the table scatter that follows.
template <typename T, int F, bool Dense, bool NeedPoints>
void backward_level(const ChunkPoints<T>& cp, int n, const T* __restrict tab, const Level& lv, uint32_t mask,
                    const T* __restrict g, T* __restrict gx, T* __restrict gy, T* __restrict gz,
                    uint32_t* __restrict rows, T* __restrict weights) {
  const T resf = static_cast<T>(lv.res);
  const uint32_t last = lv.res - 1;
#pragma omp simd
  for (int p = 0; p < n; ++p) {
    uint32_t ix, iy, iz;
    T fx, fy, fz;
    cell(cp.x[p], resf, last, ix, fx);
    cell(cp.y[p], resf, last, iy, fy);
    cell(cp.z[p], resf, last, iz, fz);
    T dx = 0, dy = 0, dz = 0;
#pragma GCC unroll 8
    for (int c = 0; c < 8; ++c) {
      const uint32_t r = corner<Dense>(c, ix, iy, iz, lv, mask);
      rows[c * kChunk + p] = r;
      weights[c * kChunk + p] = weight(c, fx, fy, fz);
      if constexpr (NeedPoints) {
        // dot = <upstream gradient, corner features>; the weight derivatives along each axis
        // are +-(product of the other two axes' weights).
        const T* row = tab + static_cast<size_t>(r) * F;
        T dot = 0;
#pragma GCC unroll 8
        for (int f = 0; f < F; ++f) dot += g[f * kChunk + p] * row[f];
        const T wx = (c & 1) ? fx : T(1) - fx, wy = (c & 2) ? fy : T(1) - fy, wz = (c & 4) ? fz : T(1) - fz;
        dx += ((c & 1) ? dot : -dot) * wy * wz;
        dy += ((c & 2) ? dot : -dot) * wx * wz;
        dz += ((c & 4) ? dot : -dot) * wx * wy;
      }
    }
    if constexpr (NeedPoints) {
      gx[p] += resf * dx;
      gy[p] += resf * dy;
      gz[p] += resf * dz;
    }
  }
}

template <typename T, int F>
void backward_impl(const T* grad, const T* points, const T* tables, T* grad_tables, T* grad_points, int64_t batch,
                   int64_t n, int64_t table_size, const std::vector<Level>& levels) {
  const int L = static_cast<int>(levels.size());
  const int width = L * F;
  const auto mask = static_cast<uint32_t>(table_size - 1);
  const int64_t table_numel = L * table_size * F;
  const int64_t chunks = (n + kChunk - 1) / kChunk;
  const int threads = static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(at::get_num_threads(), chunks)));
  // Per-thread accumulators for the table gradient (thread 0 writes straight into the output):
  // the tables are small, so private copies plus a reduction beat atomics and cannot race.
  std::vector<T> scratch(grad_tables ? static_cast<size_t>(threads - 1) * table_numel : 0);
#pragma omp parallel num_threads(threads)
  {
    const int tid = omp_get_thread_num();
    ChunkPoints<T> cp;
    alignas(64) T gx[kChunk], gy[kChunk], gz[kChunk];
    std::vector<T> g(static_cast<size_t>(width) * kChunk);
    std::vector<uint32_t> rows(8 * kChunk);
    std::vector<T> weights(8 * kChunk);
    for (int64_t b = 0; b < batch; ++b) {
      T* acc = nullptr;
      if (grad_tables) {
        acc = tid == 0 ? grad_tables + b * table_numel : scratch.data() + (tid - 1) * table_numel;
        if (tid != 0) std::fill(acc, acc + table_numel, T(0));
      }
      const T* obj_tables = tables + b * table_numel;
#pragma omp for schedule(static)
      for (int64_t chunk = 0; chunk < chunks; ++chunk) {
        const int64_t p0 = chunk * kChunk;
        const int cn = static_cast<int>(std::min<int64_t>(kChunk, n - p0));
        const T* pts = points + (b * n + p0) * 3;
        cp.load(pts, cn);
        const T* gsrc = grad + (b * n + p0) * width;
        for (int p = 0; p < cn; ++p) {
          for (int j = 0; j < width; ++j) g[static_cast<size_t>(j) * kChunk + p] = gsrc[p * width + j];
        }
        std::fill(gx, gx + cn, T(0));
        std::fill(gy, gy + cn, T(0));
        std::fill(gz, gz + cn, T(0));
        for (int l = 0; l < L; ++l) {
          const T* tab = obj_tables + l * table_size * F;
          const T* gl = g.data() + static_cast<size_t>(l) * F * kChunk;
          const Level& lv = levels[l];
          if (grad_points) {
            if (lv.dense) {
              backward_level<T, F, true, true>(cp, cn, tab, lv, mask, gl, gx, gy, gz, rows.data(), weights.data());
            } else {
              backward_level<T, F, false, true>(cp, cn, tab, lv, mask, gl, gx, gy, gz, rows.data(), weights.data());
            }
          } else {
            if (lv.dense) {
              backward_level<T, F, true, false>(cp, cn, tab, lv, mask, gl, gx, gy, gz, rows.data(), weights.data());
            } else {
              backward_level<T, F, false, false>(cp, cn, tab, lv, mask, gl, gx, gy, gz, rows.data(), weights.data());
            }
          }
          if (acc) {
            T* lacc = acc + l * table_size * F;
            for (int c = 0; c < 8; ++c) {
              const uint32_t* rc = rows.data() + c * kChunk;
              const T* wc = weights.data() + c * kChunk;
              for (int p = 0; p < cn; ++p) {
                T* dst = lacc + static_cast<size_t>(rc[p]) * F;
#pragma GCC unroll 8
                for (int f = 0; f < F; ++f) dst[f] += wc[p] * gl[f * kChunk + p];
              }
            }
          }
        }
        if (grad_points) {
          T* gp = grad_points + (b * n + p0) * 3;
          for (int p = 0; p < cn; ++p) {
            gp[3 * p + 0] = gx[p] * inside01(pts[3 * p + 0]);
            gp[3 * p + 1] = gy[p] * inside01(pts[3 * p + 1]);
            gp[3 * p + 2] = gz[p] * inside01(pts[3 * p + 2]);
          }
        }
      }  // implicit barrier: every thread's accumulator for object b is complete
      if (grad_tables && threads > 1) {
        T* out = grad_tables + b * table_numel;
#pragma omp for schedule(static)
        for (int64_t e = 0; e < table_numel; ++e) {
          T s = out[e];
          for (int t = 0; t < threads - 1; ++t) s += scratch[t * table_numel + e];
          out[e] = s;
        }
      }
    }
  }
}

void check_inputs(const at::Tensor& points, const at::Tensor& tables, c10::IntArrayRef resolutions,
                  c10::IntArrayRef dense) {
  TORCH_CHECK(points.device().is_cpu() && tables.device().is_cpu(), "hashgrid kernel runs on CPU tensors");
  TORCH_CHECK(points.dim() == 3 && points.size(2) == 3, "points must be [B, N, 3]");
  TORCH_CHECK(tables.dim() == 4 && tables.size(0) == points.size(0), "tables must be [B, L, T, F]");
  TORCH_CHECK(points.is_contiguous() && tables.is_contiguous(), "points and tables must be contiguous");
  TORCH_CHECK(points.scalar_type() == tables.scalar_type(), "points and tables must share a dtype");
  TORCH_CHECK(static_cast<int64_t>(resolutions.size()) == tables.size(1) &&
                  static_cast<int64_t>(dense.size()) == tables.size(1),
              "one resolution and dense flag per level");
  const int64_t t = tables.size(1) > 0 ? tables.size(2) : 1;
  TORCH_CHECK(t > 0 && (t & (t - 1)) == 0 && t <= (int64_t(1) << 24), "table size must be a power of two <= 2^24");
  for (auto r : resolutions) TORCH_CHECK(r >= 1 && r < (int64_t(1) << 20), "level resolution out of range");
}

template <typename T>
using ForwardFn = void (*)(const T*, const T*, T*, int64_t, int64_t, int64_t, const std::vector<Level>&);
template <typename T>
using BackwardFn = void (*)(const T*, const T*, const T*, T*, T*, int64_t, int64_t, int64_t,
                            const std::vector<Level>&);

// Feature widths get their own instantiation so the per-corner feature loop fully unrolls.
template <typename T>
ForwardFn<T> forward_for(int64_t f) {
  switch (f) {
    case 1: return forward_impl<T, 1>;
    case 2: return forward_impl<T, 2>;
    case 4: return forward_impl<T, 4>;
    case 8: return forward_impl<T, 8>;
    default: TORCH_CHECK(false, "hashgrid kernel supports 1, 2, 4 or 8 features per level, got ", f);
  }
}

template <typename T>
BackwardFn<T> backward_for(int64_t f) {
  switch (f) {
    case 1: return backward_impl<T, 1>;
    case 2: return backward_impl<T, 2>;
    case 4: return backward_impl<T, 4>;
    case 8: return backward_impl<T, 8>;
    default: TORCH_CHECK(false, "hashgrid kernel supports 1, 2, 4 or 8 features per level, got ", f);
  }
}

at::Tensor hashgrid_forward(const at::Tensor& points, const at::Tensor& tables, c10::IntArrayRef resolutions,
                            c10::IntArrayRef dense) {
  check_inputs(points, tables, resolutions, dense);
  const int64_t B = points.size(0), N = points.size(1), L = tables.size(1), T = tables.size(2), F = tables.size(3);
  auto out = at::empty({B, N, L * F}, points.options());
  if (out.numel() == 0) return out;
  const auto levels = make_levels(resolutions, dense);
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "hashgrid_forward", [&] {
    forward_for<scalar_t>(F)(points.const_data_ptr<scalar_t>(), tables.const_data_ptr<scalar_t>(),
                             out.mutable_data_ptr<scalar_t>(), B, N, T, levels);
  });
  return out;
}

std::tuple<at::Tensor, at::Tensor> hashgrid_backward(const at::Tensor& grad, const at::Tensor& points,
                                                     const at::Tensor& tables, c10::IntArrayRef resolutions,
                                                     c10::IntArrayRef dense, bool need_tables,
                                                     bool need_points) {
  check_inputs(points, tables, resolutions, dense);
  const int64_t B = points.size(0), N = points.size(1), L = tables.size(1), T = tables.size(2), F = tables.size(3);
  TORCH_CHECK(grad.is_contiguous() && grad.scalar_type() == points.scalar_type() && grad.dim() == 3 &&
                  grad.size(0) == B && grad.size(1) == N && grad.size(2) == L * F,
              "grad must be a contiguous [B, N, L*F] tensor of the points' dtype");
  // Outputs that are not requested stay empty.
  auto grad_tables = need_tables ? at::zeros(tables.sizes(), tables.options()) : at::empty({0}, tables.options());
  auto grad_points = need_points ? at::empty(points.sizes(), points.options()) : at::empty({0}, points.options());
  if (N == 0 || L == 0 || !(need_tables || need_points)) {
    if (need_points) grad_points.zero_();
    return {grad_tables, grad_points};
  }
  const auto levels = make_levels(resolutions, dense);
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "hashgrid_backward", [&] {
    backward_for<scalar_t>(F)(grad.const_data_ptr<scalar_t>(), points.const_data_ptr<scalar_t>(),
                              tables.const_data_ptr<scalar_t>(),
                              need_tables ? grad_tables.mutable_data_ptr<scalar_t>() : nullptr,
                              need_points ? grad_points.mutable_data_ptr<scalar_t>() : nullptr, B, N, T, levels);
  });
  return {grad_tables, grad_points};
}

}  // namespace

TORCH_LIBRARY(hypnerf_hashgrid, m) {
  m.def("forward(Tensor points, Tensor tables, int[] resolutions, int[] dense) -> Tensor");
  m.def(
      "backward(Tensor grad, Tensor points, Tensor tables, int[] resolutions, int[] dense, bool need_tables, "
      "bool need_points) -> (Tensor, Tensor)");
}

TORCH_LIBRARY_IMPL(hypnerf_hashgrid, CPU, m) {
  m.impl("forward", hashgrid_forward);
  m.impl("backward", hashgrid_backward);
}
