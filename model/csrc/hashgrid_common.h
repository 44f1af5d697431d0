// Shared definitions of the hash-grid kernels: level constants, the clamping rule, cell lookup,
// corner rows and trilinear weights. These encode the semantics documented in model/encoding.py;
// every code path (portable and AVX-512) is built from them.
#pragma once

#include <algorithm>
#include <cstdint>
#include <vector>

namespace hashgrid {

constexpr uint32_t kPrimeY = 2654435761u;
constexpr uint32_t kPrimeZ = 805459861u;
// Points per chunk: a chunk's coordinates, the current level's table (16 KB at T = 2^11, F = 2)
// and the chunk's output rows stay in L1/L2 while every level is processed.
constexpr int kChunk = 64;
// Chunk arrays are padded to a multiple of this many points so vector loops need no remainder.
constexpr int kPad = 16;

struct Level {
  uint32_t res;       // cells per axis (res + 1 vertices)
  uint32_t stride_y;  // dense row strides: res + 1 and (res + 1)^2
  uint32_t stride_z;
  bool dense;
};

// Clamp into [0, 1]; the comparisons are false for NaN, which therefore maps to 0.
template <typename T>
inline T clamp01(T x) {
  return x >= T(0) ? (x <= T(1) ? x : T(1)) : T(0);
}

// 1 where the point gradient passes (inside [0, 1], bounds included), else 0.
template <typename T>
inline T inside01(T x) {
  return (x >= T(0) && x <= T(1)) ? T(1) : T(0);
}

// Cell index and fraction of a clamped coordinate at a level with last cell `last` = res - 1.
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

// A chunk's points, clamped, in structure-of-arrays layout; padding points sit at the origin.
template <typename T>
struct ChunkPoints {
  alignas(64) T x[kChunk];
  alignas(64) T y[kChunk];
  alignas(64) T z[kChunk];
  int n = 0;       // real points
  int padded = 0;  // n rounded up to kPad

  void load(const T* pts, int count) {
    n = count;
    padded = (count + kPad - 1) / kPad * kPad;
    for (int p = 0; p < count; ++p) {
      x[p] = clamp01(pts[3 * p + 0]);
      y[p] = clamp01(pts[3 * p + 1]);
      z[p] = clamp01(pts[3 * p + 2]);
    }
    for (int p = count; p < padded; ++p) x[p] = y[p] = z[p] = T(0);
  }
};

// Where one chunk's data lives for a level: its points, the object's table for the level, and
// row-major [point][L*F] views of the output or upstream gradient starting at the level's column.
template <typename T>
struct LevelJob {
  const ChunkPoints<T>* points;
  const T* table;  // [T, F] of this level
  const Level* level;
  uint32_t mask;   // T - 1
  int width;       // L * F: distance between consecutive points' rows
};

}  // namespace hashgrid
