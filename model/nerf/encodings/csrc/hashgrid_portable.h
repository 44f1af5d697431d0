// Portable per-level hash-grid kernels for any float type and feature width: plain C++ whose
// point loops the compiler vectorises (OpenMP simd). Used for float64, for widths other than
// F = 2, and on CPUs without AVX-512.
#pragma once

#include "hashgrid_common.h"

namespace hashgrid {

template <typename T, int F>
struct PortableLevels {
  template <bool Dense>
  static void forward_rows(const LevelJob<T>& job, T* __restrict out) {
    const ChunkPoints<T>& cp = *job.points;
    const T* __restrict tab = job.table;
    const Level lv = *job.level;
    const T resf = static_cast<T>(lv.res);
    const uint32_t last = lv.res - 1, mask = job.mask;
    const int width = job.width;
#pragma omp simd
    for (int p = 0; p < cp.n; ++p) {
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
      for (int f = 0; f < F; ++f) out[p * width + f] = acc[f];
    }
  }

  static void forward(const LevelJob<T>& job, T* out) {
    if (job.level->dense) {
      forward_rows<true>(job, out);
    } else {
      forward_rows<false>(job, out);
    }
  }

  // Point gradients accumulate into gx/gy/gz (when given); each corner's row and weight are kept
  // so the table gradient can be scattered afterwards in a plain loop (a vector scatter-add would
  // race on rows shared by several points).
  template <bool Dense, bool NeedPoints>
  static void backward_rows(const LevelJob<T>& job, const T* __restrict grad, uint32_t* __restrict rows,
                            T* __restrict weights, T* __restrict gx, T* __restrict gy, T* __restrict gz) {
    const ChunkPoints<T>& cp = *job.points;
    const T* __restrict tab = job.table;
    const Level lv = *job.level;
    const T resf = static_cast<T>(lv.res);
    const uint32_t last = lv.res - 1, mask = job.mask;
    const int width = job.width;
#pragma omp simd
    for (int p = 0; p < cp.n; ++p) {
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
          // dot = <upstream gradient, corner features>; the weight's derivative along an axis
          // is +-(product of the other two axes' weights).
          const T* row = tab + static_cast<size_t>(r) * F;
          T dot = 0;
#pragma GCC unroll 8
          for (int f = 0; f < F; ++f) dot += grad[p * width + f] * row[f];
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

  static void backward(const LevelJob<T>& job, const T* grad, T* table_grad, T* gx, T* gy, T* gz) {
    alignas(64) uint32_t rows[8 * kChunk];
    alignas(64) T weights[8 * kChunk];
    const bool dense = job.level->dense;
    if (gx) {
      dense ? backward_rows<true, true>(job, grad, rows, weights, gx, gy, gz)
            : backward_rows<false, true>(job, grad, rows, weights, gx, gy, gz);
    } else {
      dense ? backward_rows<true, false>(job, grad, rows, weights, gx, gy, gz)
            : backward_rows<false, false>(job, grad, rows, weights, gx, gy, gz);
    }
    if (!table_grad) return;
    const int n = job.points->n, width = job.width;
    for (int c = 0; c < 8; ++c) {
      for (int p = 0; p < n; ++p) {
        T* dst = table_grad + static_cast<size_t>(rows[c * kChunk + p]) * F;
        const T w = weights[c * kChunk + p];
#pragma GCC unroll 8
        for (int f = 0; f < F; ++f) dst[f] += w * grad[p * width + f];
      }
    }
  }
};

}  // namespace hashgrid
