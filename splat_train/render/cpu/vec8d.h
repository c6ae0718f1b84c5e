// Eight doubles per vector (GCC/Clang vector extension) and the elementwise helpers that the
// per-Gaussian SIMD passes share: the fused projection + SH (project.cpp) and the footprint
// pass of the blend kernel (raster.cpp). Each lane computes what the scalar double code
// computes; sqrt, floor and ceil map to the widest instructions the build flags allow (IEEE exact
// at every level, so the result does not depend on the SIMD level).
//
// Included by the kernel sources; the build cache key covers this header too
// (splat_train/render/cpu/build.py), so editing it rebuilds both kernels.
#pragma once

#include <cmath>
#include <cstdint>
#include <cstring>
#if defined(__AVX2__) || defined(__AVX512F__) || defined(__SSE2__)
#include <immintrin.h>
#endif

namespace vec8d {

constexpr int LN = 8;  // lanes (Gaussians per vector)
typedef double D __attribute__((vector_size(8 * LN)));
typedef int64_t Mk __attribute__((vector_size(8 * LN)));

inline D bc(double x) { return D{x, x, x, x, x, x, x, x}; }
// std::max / std::min semantics (the first argument wins ties and NaN comparisons)
inline D vmax(D a, D b) { return a < b ? b : a; }
inline D vmin(D a, D b) { return b < a ? b : a; }
inline D vsqrt(D x) {
  D r;
#if defined(__AVX512F__)
  __m512d v;
  std::memcpy(&v, &x, 64);
  v = _mm512_maskz_sqrt_pd(0xFF, v);  // (masked: the unmasked form trips -Wuninitialized in GCC 12's header)
  std::memcpy(&r, &v, 64);
#elif defined(__AVX__)
  __m256d v[2];
  std::memcpy(v, &x, 64);
  v[0] = _mm256_sqrt_pd(v[0]);
  v[1] = _mm256_sqrt_pd(v[1]);
  std::memcpy(&r, v, 64);
#elif defined(__SSE2__)
  __m128d v[4];
  std::memcpy(v, &x, 64);
  for (int k = 0; k < 4; ++k) v[k] = _mm_sqrt_pd(v[k]);
  std::memcpy(&r, v, 64);
#else
  for (int l = 0; l < LN; ++l) r[l] = std::sqrt(x[l]);
#endif
  return r;
}
// floor / ceil (mode 1 / 2 of the rounding instructions)
template <int MODE> inline D vround(D x) {
  D r;
#if defined(__AVX512F__)
  __m512d v;
  std::memcpy(&v, &x, 64);
  v = _mm512_maskz_roundscale_pd(0xFF, v, MODE | _MM_FROUND_NO_EXC);
  std::memcpy(&r, &v, 64);
#elif defined(__AVX__)
  __m256d v[2];
  std::memcpy(v, &x, 64);
  v[0] = _mm256_round_pd(v[0], MODE | _MM_FROUND_NO_EXC);
  v[1] = _mm256_round_pd(v[1], MODE | _MM_FROUND_NO_EXC);
  std::memcpy(&r, v, 64);
#else
  for (int l = 0; l < LN; ++l) r[l] = MODE == 1 ? std::floor(x[l]) : std::ceil(x[l]);
#endif
  return r;
}
inline D vfloor(D x) { return vround<1>(x); }
inline D vceil(D x) { return vround<2>(x); }

}  // namespace vec8d
