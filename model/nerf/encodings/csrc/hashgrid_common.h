// Shared definitions of the hash-grid kernels: level constants, the clamping rule, cell lookup,
// corner rows and trilinear weights. These encode the semantics documented in model/encoding.py;
// the portable path uses them directly and the AVX-512 path mirrors them lane by lane.
#pragma once

#include <algorithm>
#include <cstdint>

namespace hashgrid {

constexpr uint32_t kPrimeY = 2654435761u;
constexpr uint32_t kPrimeZ = 805459861u;
// Points per chunk: all levels are processed for one chunk before the next, so its coordinates
// and output rows stay in cache; measured 5-10% faster than 64 points, flat up to 1024.
constexpr int kChunk = 256;
// Chunk arrays are padded to a multiple of this many points so vector loads stay in bounds.
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

// One chunk at one level: its points and the object's table for the level. The output and the
// upstream gradient are passed alongside as pointers to the chunk's first row at the level's
// column, rows being `width` apart.
template <typename T>
struct LevelJob {
  const ChunkPoints<T>* points;
  const T* table;  // [T, F] of this level
  const Level* level;
  uint32_t mask;   // T - 1
  int width;       // L * F: distance between consecutive points' rows
};

}  // namespace hashgrid
