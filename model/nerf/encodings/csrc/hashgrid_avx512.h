// AVX-512 per-level hash-grid kernels for float32 with F = 2 features (the paper setting).
//
// Eight points are processed per vector. A table row of two floats is one 64-bit unit, so a
// 512-bit register holds the rows of 8 points side by side ("pair layout": lanes 2k, 2k + 1
// belong to point k) and a corner costs 8 scalar 64-bit loads; on the CPU measured (AMD Zen 4)
// these beat hardware gathers, and the compiler's own vectorisation of the portable loop, which
// gathers float by float, ran at about half this speed. Cell and row arithmetic runs on 8 x uint32
// in 256-bit registers (see hashgrid.cpp for why uint32 hashing is exact) and chooses the same
// cells as the portable path; sums differ from it only by rounding (fused multiply-adds).
#pragma once

#if defined(__AVX512F__) && defined(__AVX2__)
#define HASHGRID_HAVE_AVX512 1

#include <immintrin.h>

#include <cstring>

#include "hashgrid_common.h"

namespace hashgrid {

struct Avx512PairLevels {
  // Per-axis data of 8 points at one level: corner rows and the weights in pair layout.
  struct Corners {
    alignas(32) uint32_t rows[8][8];
    __m512 wx[2], wy[2], wz[2];
  };

  static inline __m512 duplicate_pairs(__m256 v) {
    const __m512i dup = _mm512_set_epi32(7, 7, 6, 6, 5, 5, 4, 4, 3, 3, 2, 2, 1, 1, 0, 0);
    return _mm512_permutexvar_ps(dup, _mm512_castps256_ps512(v));
  }

  // Same arithmetic as hashgrid::cell: pos = x * res, i = min(trunc(pos), res - 1), f = pos - i.
  static inline void axis(const float* x, __m256 resf, __m256i last, __m256i& i, __m512 w[2]) {
    const __m256 pos = _mm256_mul_ps(_mm256_load_ps(x), resf);
    i = _mm256_min_epu32(_mm256_cvttps_epi32(pos), last);
    const __m512 f = duplicate_pairs(_mm256_sub_ps(pos, _mm256_cvtepi32_ps(i)));
    w[0] = _mm512_sub_ps(_mm512_set1_ps(1.0f), f);
    w[1] = f;
  }

  static inline void locate(const LevelJob<float>& job, int p, Corners& k) {
    const Level& lv = *job.level;
    const __m256 resf = _mm256_set1_ps(static_cast<float>(lv.res));
    const __m256i last = _mm256_set1_epi32(static_cast<int>(lv.res - 1));
    const ChunkPoints<float>& cp = *job.points;
    __m256i ix, iy, iz;
    axis(cp.x + p, resf, last, ix, k.wx);
    axis(cp.y + p, resf, last, iy, k.wy);
    axis(cp.z + p, resf, last, iz, k.wz);
    const __m256i one = _mm256_set1_epi32(1);
    if (lv.dense) {
      const __m256i sy = _mm256_set1_epi32(static_cast<int>(lv.stride_y));
      const __m256i sz = _mm256_set1_epi32(static_cast<int>(lv.stride_z));
      const __m256i base =
          _mm256_add_epi32(ix, _mm256_add_epi32(_mm256_mullo_epi32(iy, sy), _mm256_mullo_epi32(iz, sz)));
#pragma GCC unroll 8
      for (int c = 0; c < 8; ++c) {
        const uint32_t off = (c & 1) + ((c >> 1) & 1) * lv.stride_y + ((c >> 2) & 1) * lv.stride_z;
        _mm256_store_si256(reinterpret_cast<__m256i*>(k.rows[c]),
                           _mm256_add_epi32(base, _mm256_set1_epi32(static_cast<int>(off))));
      }
    } else {
      const __m256i py = _mm256_set1_epi32(static_cast<int>(kPrimeY));
      const __m256i pz = _mm256_set1_epi32(static_cast<int>(kPrimeZ));
      const __m256i mask = _mm256_set1_epi32(static_cast<int>(job.mask));
      const __m256i hx[2] = {ix, _mm256_add_epi32(ix, one)};
      const __m256i y0 = _mm256_mullo_epi32(iy, py), z0 = _mm256_mullo_epi32(iz, pz);
      const __m256i hy[2] = {y0, _mm256_add_epi32(y0, py)};
      const __m256i hz[2] = {z0, _mm256_add_epi32(z0, pz)};
#pragma GCC unroll 8
      for (int c = 0; c < 8; ++c) {
        const __m256i h = _mm256_xor_si256(_mm256_xor_si256(hx[c & 1], hy[(c >> 1) & 1]), hz[(c >> 2) & 1]);
        _mm256_store_si256(reinterpret_cast<__m256i*>(k.rows[c]), _mm256_and_si256(h, mask));
      }
    }
  }

  static inline __m512 corner_weight(const Corners& k, int c) {
    return _mm512_mul_ps(_mm512_mul_ps(k.wx[c & 1], k.wy[(c >> 1) & 1]), k.wz[(c >> 2) & 1]);
  }

  // Rows r(0..7) of two floats from `base` in pair layout. __m64 pointers may alias floats.
  template <typename Index>
  static inline __m512 load_pairs(const float* base, Index r) {
    auto at = [&](int j) { return reinterpret_cast<const __m64*>(base + 2 * static_cast<size_t>(r(j))); };
    const __m128 a = _mm_loadh_pi(_mm_loadl_pi(_mm_setzero_ps(), at(0)), at(1));
    const __m128 b = _mm_loadh_pi(_mm_loadl_pi(_mm_setzero_ps(), at(2)), at(3));
    const __m128 c = _mm_loadh_pi(_mm_loadl_pi(_mm_setzero_ps(), at(4)), at(5));
    const __m128 d = _mm_loadh_pi(_mm_loadl_pi(_mm_setzero_ps(), at(6)), at(7));
    const __m256 lo = _mm256_insertf128_ps(_mm256_castps128_ps256(a), b, 1);
    const __m256 hi = _mm256_insertf128_ps(_mm256_castps128_ps256(c), d, 1);
    return _mm512_castpd_ps(_mm512_insertf64x4(_mm512_castpd256_pd512(_mm256_castps_pd(lo)), _mm256_castps_pd(hi), 1));
  }

  // Table rows rows[0..7]; the row numbers are read two per 64-bit load to spare load slots.
  static inline __m512 load_rows(const float* tab, const uint32_t* rows) {
    uint64_t r[4];
    std::memcpy(r, rows, sizeof(r));
    return load_pairs(tab, [&r](int j) { return static_cast<uint32_t>(r[j >> 1] >> (32 * (j & 1))); });
  }

  // The 128-bit quarter q (points 2q and 2q + 1) of a pair-layout register.
  static inline __m128 quarter(__m512 v, int q) {
    switch (q) {
      case 0: return _mm512_castps512_ps128(v);
      case 1: return _mm512_extractf32x4_ps(v, 1);
      case 2: return _mm512_extractf32x4_ps(v, 2);
      default: return _mm512_extractf32x4_ps(v, 3);
    }
  }

  static void forward(const LevelJob<float>& job, float* out) {
    const float* tab = job.table;
    const int n = job.points->n, width = job.width;
    Corners k;
    for (int p = 0; p < n; p += 8) {
      locate(job, p, k);
      __m512 acc = _mm512_mul_ps(corner_weight(k, 0), load_rows(tab, k.rows[0]));
#pragma GCC unroll 7
      for (int c = 1; c < 8; ++c) acc = _mm512_fmadd_ps(corner_weight(k, c), load_rows(tab, k.rows[c]), acc);
      // Straight from registers to the 8 output rows (no round trip through the stack).
      const int count = std::min(8, n - p);
#pragma GCC unroll 4
      for (int q = 0; q < 4; ++q) {
        const __m128 v = quarter(acc, q);
        if (2 * q < count) _mm_storel_pi(reinterpret_cast<__m64*>(out + (p + 2 * q) * width), v);
        if (2 * q + 1 < count) _mm_storeh_pi(reinterpret_cast<__m64*>(out + (p + 2 * q + 1) * width), v);
      }
    }
  }

  static void backward(const LevelJob<float>& job, const float* grad, float* table_grad, float* gx, float* gy,
                       float* gz) {
    const float* tab = job.table;
    const int n = job.points->n, width = job.width;
    const __m512i even = _mm512_set_epi32(0, 0, 0, 0, 0, 0, 0, 0, 14, 12, 10, 8, 6, 4, 2, 0);
    const float resf = static_cast<float>(job.level->res);
    Corners k;
    for (int p = 0; p < n; p += 8) {
      locate(job, p, k);
      const int count = std::min(8, n - p);
      // Upstream gradient rows of the 8 points (padding lanes re-read the last real point).
      const int row_pairs = width / 2;
      const __m512 g =
          load_pairs(grad, [=](int j) { return static_cast<size_t>(p + std::min(j, count - 1)) * row_pairs; });
      if (table_grad) {
#pragma GCC unroll 8
        for (int c = 0; c < 8; ++c) {
          const __m512 contrib = _mm512_mul_ps(corner_weight(k, c), g);
          // One point at a time, in order: two points may share a row.
#pragma GCC unroll 4
          for (int q = 0; q < 4; ++q) {
            const __m128 lo = quarter(contrib, q);
            const __m128 parts[2] = {lo, _mm_movehl_ps(lo, lo)};
#pragma GCC unroll 2
            for (int h = 0; h < 2; ++h) {
              if (2 * q + h >= count) break;
              auto* dst = reinterpret_cast<__m64*>(table_grad + 2 * static_cast<size_t>(k.rows[c][2 * q + h]));
              _mm_storel_pi(dst, _mm_add_ps(_mm_loadl_pi(_mm_setzero_ps(), dst), parts[h]));
            }
          }
        }
      }
      if (gx) {
        // dot_c = <g, row_c> in both lanes of each pair (swap the pair's halves and add).
        __m512 dot[8];
#pragma GCC unroll 8
        for (int c = 0; c < 8; ++c) {
          const __m512 prod = _mm512_mul_ps(g, load_rows(tab, k.rows[c]));
          dot[c] = _mm512_add_ps(prod, _mm512_permute_ps(prod, 0xB1));
        }
        // Derivative of the trilinear weights: differences along an axis, weighted by the
        // other two axes.
        __m512 dx = _mm512_setzero_ps(), dy = _mm512_setzero_ps(), dz = _mm512_setzero_ps();
#pragma GCC unroll 2
        for (int a = 0; a < 2; ++a) {
#pragma GCC unroll 2
          for (int b = 0; b < 2; ++b) {
            dx = _mm512_fmadd_ps(_mm512_sub_ps(dot[1 | a << 1 | b << 2], dot[a << 1 | b << 2]),
                                 _mm512_mul_ps(k.wy[a], k.wz[b]), dx);
            dy = _mm512_fmadd_ps(_mm512_sub_ps(dot[a | 2 | b << 2], dot[a | b << 2]),
                                 _mm512_mul_ps(k.wx[a], k.wz[b]), dy);
            dz = _mm512_fmadd_ps(_mm512_sub_ps(dot[a | b << 1 | 4], dot[a | b << 1]),
                                 _mm512_mul_ps(k.wx[a], k.wy[b]), dz);
          }
        }
        const __m256 res = _mm256_set1_ps(resf);
        auto accumulate = [&](float* dst, __m512 d) {
          const __m256 v = _mm512_castps512_ps256(_mm512_permutexvar_ps(even, d));
          _mm256_store_ps(dst + p, _mm256_fmadd_ps(v, res, _mm256_load_ps(dst + p)));
        };
        accumulate(gx, dx);
        accumulate(gy, dy);
        accumulate(gz, dz);
      }
    }
  }
};

}  // namespace hashgrid

#endif
