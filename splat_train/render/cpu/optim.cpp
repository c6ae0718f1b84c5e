// The optimizer side of a training iteration on the kernel's threads: one Adam step
// over several float32 parameter tensors (splat_adam_f32) and the densification statistics
// (splat_densify_stats_f32).
//
// Built and loaded like raster.cpp (plain C ABI, ctypes, no torch headers or OpenMP).
// torch.optim.Adam (fused) runs on torch's intra-op threads, which the trainer keeps at one:
// torch's OpenMP workers spin after each parallel region on the cores the rasterizer's own
// threads need next (Adam on two torch threads took 7 -> 6 ms but the render after it 36 -> 40
// ms). This kernel runs on the rasterizer's threads (splat_train.render.cpu.build.run_threaded),
// which leave no spinning worker behind. Adam is memory-bound (59 floats per Gaussian read
// four times and written three times: ~330 MB per step at 200k Gaussians), and one core does
// not reach the machine's bandwidth.
//
// Per element, torch.optim.Adam without weight decay, amsgrad or maximize (float32 arithmetic,
// the step's scalars in double as torch computes them):
//   m <- m + (1 - beta1) (g - m)               (torch: exp_avg.lerp_(grad, 1 - beta1))
//   v <- beta2 v + (1 - beta2) g^2
//   p <- p - step_size m / (sqrt(v) / sqrt(bc2) + eps),  step_size = lr / bc1,
// bc1 = 1 - beta1^t and bc2 = 1 - beta2^t at the step t after the increment. Every element is
// independent, so the result does not depend on the thread count; it agrees with torch's
// fused Adam to float32 rounding (tests/test_train_adam.py).

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#if defined(__AVX__)
#include <immintrin.h>
#endif

namespace {
constexpr int64_t CHUNK = 1 << 14;  // elements per work item (a multiple of 8)
typedef float V8 __attribute__((vector_size(32)));

// Eight square roots. (A plain loop over std::sqrt was not vectorised: sqrt may set errno, and
// the scalar loop ran ~3x slower than torch's one-thread Adam.)
inline V8 vsqrt(V8 x) {
#if defined(__AVX__)
  __m256 r;
  std::memcpy(&r, &x, 32);
  r = _mm256_sqrt_ps(r);
  std::memcpy(&x, &r, 32);
#else
  for (int l = 0; l < 8; ++l) x[l] = std::sqrt(x[l]);
#endif
  return x;
}

// The update of one element (or eight, X = V8): the same operations in the same order.
template <typename X>
inline void adam_update(X& p, X g, X& m, X& v, float w1, float b2, float w2, float ss, float bc, float e) {
  m = m + w1 * (g - m);
  v = b2 * v + w2 * g * g;
  X r;
  if constexpr (sizeof(X) == sizeof(float)) {
    r = std::sqrt(v);
  } else {
    r = vsqrt(v);
  }
  p = p - ss * m / (r / bc + e);
}
}  // namespace

extern "C" {

int splat_optim_abi_version() { return 1; }

// nt tensors: p[j], g[j], m[j], v[j] (float32, contiguous) of n[j] elements, with their own
// step_size[j] and sqrt(bc2)[j]; chunk_start[j] = the first work item of tensor j (the running
// sum of ceil(n / CHUNK)), chunk_start[nt] = all items. counter: the shared work counter.
void splat_adam_f32(int64_t nt, float* const* p, const float* const* g, float* const* m, float* const* v,
                    const int64_t* n, const double* step_size, const double* bc2_sqrt, double beta1, double beta2,
                    double eps, const int64_t* chunk_start, int64_t* counter) {
  const float b2 = (float)beta2, w1 = (float)(1.0 - beta1), w2 = (float)(1.0 - beta2);
  const float e = (float)eps;
  for (int64_t c; (c = __atomic_fetch_add(counter, 1, __ATOMIC_RELAXED)) < chunk_start[nt];) {
    const int64_t j = std::upper_bound(chunk_start, chunk_start + nt + 1, c) - chunk_start - 1;
    const int64_t i0 = (c - chunk_start[j]) * CHUNK, i1 = std::min(n[j], i0 + CHUNK);
    float* __restrict pj = p[j];
    const float* __restrict gj = g[j];
    float* __restrict mj = m[j];
    float* __restrict vj = v[j];
    const float ss = (float)step_size[j], bc = (float)bc2_sqrt[j];
    int64_t i = i0;
    for (; i + 8 <= i1; i += 8) {
      V8 pv, gv, mv, vv;
      std::memcpy(&pv, pj + i, 32);
      std::memcpy(&gv, gj + i, 32);
      std::memcpy(&mv, mj + i, 32);
      std::memcpy(&vv, vj + i, 32);
      adam_update(pv, gv, mv, vv, w1, b2, w2, ss, bc, e);
      std::memcpy(pj + i, &pv, 32);
      std::memcpy(mj + i, &mv, 32);
      std::memcpy(vj + i, &vv, 32);
    }
    for (; i < i1; ++i) {
      float pv = pj[i], mv = mj[i], vv = vj[i];
      adam_update(pv, gj[i], mv, vv, w1, b2, w2, ss, bc, e);
      pj[i] = pv;
      mj[i] = mv;
      vj[i] = vv;
    }
  }
}

// The view-space gradient statistics of 3DGS densification for one view (the torch code of
// splat_train.densify.DensifyStrategy.update_state, which stays for other devices and dtypes):
// per Gaussian g with visible[g] and a finite norm = |(gx W / 2, gy H / 2)| (the gradient in
// NDC units): grad2d[g] += norm, count[g] += 1, max_radii[g] = max(max_radii[g], radii[g]).
// Elements independent: no dependence on the thread count. The eight [N] torch ops took
// ~2.5 ms of an iteration at 200k Gaussians on one thread.
void splat_densify_stats_f32(int64_t n, const float* grad, int64_t grad_stride, const int32_t* radii,
                             const uint8_t* visible, double sx, double sy, float* grad2d, float* count,
                             float* max_radii, int64_t* counter) {
  const float fx = (float)sx, fy = (float)sy;
  for (int64_t c; (c = __atomic_fetch_add(counter, 1, __ATOMIC_RELAXED)) * CHUNK < n;) {
    const int64_t i1 = std::min(n, (c + 1) * CHUNK);
    for (int64_t i = c * CHUNK; i < i1; ++i) {
      const float gx = grad[i * grad_stride] * fx, gy = grad[i * grad_stride + 1] * fy;
      const float nrm = std::sqrt(gx * gx + gy * gy);
      if (!visible[i] || !(std::fabs(nrm) <= 3.4028234663852886e38f)) continue;  // hidden, inf or NaN
      grad2d[i] += nrm;
      count[i] += 1.0f;
      max_radii[i] = std::max(max_radii[i], (float)radii[i]);
    }
  }
}

}  // extern "C"
