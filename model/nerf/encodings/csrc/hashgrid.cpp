// Fused multi-resolution hash encoding on CPU: forward, backward to tables, backward to points.
//
// A torch C++ extension registered as the operator namespace `hypnerf_hashgrid`, parallelised
// with OpenMP over chunks of points (the same libgomp torch uses, so torch.set_num_threads
// applies). Semantics match the pure-PyTorch reference in model/encoding.py:
//   - coordinates are clamped into [0, 1] (NaN -> 0); the point gradient is zero outside [0, 1];
//   - a level of resolution res has res + 1 vertices per axis; the cell is
//     min(floor(x * res), res - 1), so x = 1 lands in the last cell with fraction 1 and no
//     corner leaves the grid;
//   - dense levels use row x + y (res + 1) + z (res + 1)^2, hashed levels
//     (x * 1 ^ y * 2654435761 ^ z * 805459861) mod T.
// Hash products are formed in uint32: T is a power of two <= 2^24, so the low log2(T) bits of a
// product, and of an XOR of products, are the same whether taken mod 2^32 or in int64; row
// offsets into the tables are 64-bit.
//
// Each chunk of kChunk points goes through all levels, one level after another, before the next
// chunk; chunk scratch lives on the stack, so calls allocate nothing beyond the returned tensors
// and the backward's table copies. float32 with F = 2 runs the AVX-512 path where the CPU has it
// (hashgrid_avx512.h); everything else runs the portable path (hashgrid_portable.h).

#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <memory>
#include <type_traits>
#include <vector>

#include "hashgrid_avx512.h"
#include "hashgrid_common.h"
#include "hashgrid_portable.h"

namespace {

using namespace hashgrid;

std::vector<Level> make_levels(c10::IntArrayRef resolutions, c10::IntArrayRef dense) {
  std::vector<Level> levels;
  for (size_t l = 0; l < resolutions.size(); ++l) {
    const auto r = static_cast<uint32_t>(resolutions[l]);
    levels.push_back({r, r + 1, (r + 1) * (r + 1), dense[l] != 0});
  }
  return levels;
}

struct Problem {
  int64_t batch, n, table_size, features;
  const std::vector<Level>* levels;

  int num_levels() const { return static_cast<int>(levels->size()); }
  int width() const { return num_levels() * static_cast<int>(features); }
  int64_t table_numel() const { return num_levels() * table_size * features; }
  int64_t chunks() const { return (n + kChunk - 1) / kChunk; }
};

// Chunks are handed to threads on demand: on a shared machine a thread may lose its core for a
// while, and static shares would leave the other thread waiting. Outputs of different points are
// independent, so the schedule cannot change the result.
template <typename Levels, typename T>
void forward_impl(const Problem& pb, const T* points, const T* tables, T* out) {
  const int L = pb.num_levels(), width = pb.width();
  const int64_t F = pb.features, chunks = pb.chunks(), total = pb.batch * chunks;
  const auto mask = static_cast<uint32_t>(pb.table_size - 1);
#pragma omp parallel num_threads(at::get_num_threads()) if (total > 1)
  {
    ChunkPoints<T> cp;
#pragma omp for schedule(dynamic, 1)
    for (int64_t job = 0; job < total; ++job) {
      const int64_t b = job / chunks, p0 = (job % chunks) * kChunk;
      cp.load(points + (b * pb.n + p0) * 3, static_cast<int>(std::min<int64_t>(kChunk, pb.n - p0)));
      T* rows = out + (b * pb.n + p0) * width;
      for (int l = 0; l < L; ++l) {
        const LevelJob<T> lj{&cp, tables + (b * L + l) * pb.table_size * F, &(*pb.levels)[l], mask, width};
        Levels::forward(lj, rows + l * F);
      }
    }
  }
}

// The table gradient is a scatter-add into small tables, so instead of atomics the work is cut
// into units (an object, or a contiguous run of one object's chunks) that each accumulate into
// their own copy of the object's tables; when an object has several units their copies are then
// summed in a fixed order. Units are handed to threads on demand like forward chunks; since a
// unit's sum does not depend on which thread ran it, results are deterministic for a given
// thread count. Units per object: enough to keep every thread busy, and more (up to 4 per
// thread) for load balance only while each unit keeps max(16384, 4 T) points, so that zeroing and
// summing the extra table copies stays a small part of the work and of the memory.
template <typename Levels, typename T>
void backward_impl(const Problem& pb, const T* grad, const T* points, const T* tables, T* grad_tables,
                   T* grad_points) {
  const int64_t min_unit_points = std::max<int64_t>(16384, 4 * pb.table_size);
  const int L = pb.num_levels(), width = pb.width();
  const int64_t F = pb.features, chunks = pb.chunks(), table_numel = pb.table_numel();
  const auto mask = static_cast<uint32_t>(pb.table_size - 1);
  const int threads = at::get_num_threads();
  auto ceil_div = [](int64_t a, int64_t b) { return (a + b - 1) / b; };
  const int64_t balanced = std::min(ceil_div(4 * threads, pb.batch), pb.n / min_unit_points);
  const int64_t per_object = std::min(chunks, std::max(ceil_div(threads, pb.batch), balanced));
  const int64_t units = pb.batch * per_object;
  const bool reduce = grad_tables && per_object > 1;
  std::unique_ptr<T[]> scratch(reduce ? new T[units * table_numel] : nullptr);
#pragma omp parallel num_threads(threads)
  {
    ChunkPoints<T> cp;
    alignas(64) T gx[kChunk], gy[kChunk], gz[kChunk];
#pragma omp for schedule(dynamic, 1)
    for (int64_t unit = 0; unit < units; ++unit) {
      const int64_t b = unit / per_object, part = unit % per_object;
      T* acc = nullptr;
      if (grad_tables) {
        acc = reduce ? scratch.get() + unit * table_numel : grad_tables + b * table_numel;
        std::fill(acc, acc + table_numel, T(0));
      }
      for (int64_t chunk = part * chunks / per_object; chunk < (part + 1) * chunks / per_object; ++chunk) {
        const int64_t p0 = chunk * kChunk;
        const T* pts = points + (b * pb.n + p0) * 3;
        cp.load(pts, static_cast<int>(std::min<int64_t>(kChunk, pb.n - p0)));
        std::fill(gx, gx + kChunk, T(0));
        std::fill(gy, gy + kChunk, T(0));
        std::fill(gz, gz + kChunk, T(0));
        const T* rows = grad + (b * pb.n + p0) * width;
        for (int l = 0; l < L; ++l) {
          const int64_t offset = l * pb.table_size * F;
          const LevelJob<T> lj{&cp, tables + b * table_numel + offset, &(*pb.levels)[l], mask, width};
          Levels::backward(lj, rows + l * F, acc ? acc + offset : nullptr, grad_points ? gx : nullptr, gy, gz);
        }
        if (grad_points) {
          T* gp = grad_points + (b * pb.n + p0) * 3;
          for (int p = 0; p < cp.n; ++p) {
            gp[3 * p + 0] = gx[p] * inside01(pts[3 * p + 0]);
            gp[3 * p + 1] = gy[p] * inside01(pts[3 * p + 1]);
            gp[3 * p + 2] = gz[p] * inside01(pts[3 * p + 2]);
          }
        }
      }
    }  // implicit barrier: every unit is complete
    if (reduce) {
#pragma omp for collapse(2) schedule(static)
      for (int64_t b = 0; b < pb.batch; ++b) {
        for (int64_t e = 0; e < table_numel; ++e) {
          const T* copies = scratch.get() + b * per_object * table_numel + e;
          T sum = copies[0];
          for (int64_t s = 1; s < per_object; ++s) sum += copies[s * table_numel];
          grad_tables[b * table_numel + e] = sum;
        }
      }
    }
  }
}

// Picks the level kernels for a dtype and feature width; each width is its own instantiation so
// the per-corner feature loop fully unrolls.
template <typename T, typename Fn>
void with_levels(int64_t features, Fn&& fn) {
#ifdef HASHGRID_HAVE_AVX512
  if constexpr (std::is_same_v<T, float>) {
    if (features == 2) return fn(Avx512PairLevels{});
  }
#endif
  switch (features) {
    case 1: return fn(PortableLevels<T, 1>{});
    case 2: return fn(PortableLevels<T, 2>{});
    case 4: return fn(PortableLevels<T, 4>{});
    case 8: return fn(PortableLevels<T, 8>{});
    default: TORCH_CHECK(false, "hashgrid kernel supports 1, 2, 4 or 8 features per level, got ", features);
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

at::Tensor hashgrid_forward(const at::Tensor& points, const at::Tensor& tables, c10::IntArrayRef resolutions,
                            c10::IntArrayRef dense) {
  check_inputs(points, tables, resolutions, dense);
  const int64_t B = points.size(0), N = points.size(1), L = tables.size(1), T = tables.size(2), F = tables.size(3);
  auto out = at::empty({B, N, L * F}, points.options());
  if (out.numel() == 0) return out;
  const auto levels = make_levels(resolutions, dense);
  const Problem pb{B, N, T, F, &levels};
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "hashgrid_forward", [&] {
    with_levels<scalar_t>(F, [&](auto kernel) {
      forward_impl<decltype(kernel)>(pb, points.const_data_ptr<scalar_t>(), tables.const_data_ptr<scalar_t>(),
                                     out.mutable_data_ptr<scalar_t>());
    });
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
  auto grad_tables = need_tables ? at::empty(tables.sizes(), tables.options()) : at::empty({0}, tables.options());
  auto grad_points = need_points ? at::empty(points.sizes(), points.options()) : at::empty({0}, points.options());
  if (N == 0 || L == 0 || !(need_tables || need_points)) {
    grad_tables.zero_();
    grad_points.zero_();
    return {grad_tables, grad_points};
  }
  const auto levels = make_levels(resolutions, dense);
  const Problem pb{B, N, T, F, &levels};
  AT_DISPATCH_FLOATING_TYPES(points.scalar_type(), "hashgrid_backward", [&] {
    with_levels<scalar_t>(F, [&](auto kernel) {
      backward_impl<decltype(kernel)>(pb, grad.const_data_ptr<scalar_t>(), points.const_data_ptr<scalar_t>(),
                                      tables.const_data_ptr<scalar_t>(),
                                      need_tables ? grad_tables.mutable_data_ptr<scalar_t>() : nullptr,
                                      need_points ? grad_points.mutable_data_ptr<scalar_t>() : nullptr);
    });
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
