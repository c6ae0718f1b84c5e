// Tile-based Gaussian alpha blending on the CPU, SIMD across the pixels of a tile.
//
// Built by splat_train/render/cpu/raster.py with the system C++ compiler (plain C ABI through ctypes,
// no torch headers, no OpenMP). The SIMD width is chosen at load time by the build flags
// (-mavx512f ... on CPUs that have AVX-512, -mavx2 -mfma on AVX2 ones, none elsewhere): the code
// uses GCC/Clang vector extensions, one 16-lane vector per 16-pixel tile row, which the compiler
// maps to one zmm register (AVX-512), two ymm (AVX2) or four xmm (SSE2). Semantics are those of
// splat_train/render/_reference.py (3DGS forward rules) and of the scalar kernel it replaced (backend
// "cpu_v1", since deleted; benchmarks/README.md records their comparison):
//
// * Forward: per tile, Gaussians front to back; each Gaussian visits only the tile rows its
//   alpha >= 1/255 ellipse can reach, and there all 16 pixels of a row at once, with per-lane
//   masks for the skip (power > 0, alpha < 1/255) and stop (T (1 - alpha) < 1e-4) rules. A row
//   whose pixels have all stopped is skipped; the tile ends when every row has. Rows go four
//   or two per step with their exp chains interleaved and no per-row branch on the masks
//   (the loop is latency-bound: a row is one long dependency chain); the backward likewise
//   (its hit rows, below). The rasterizer's own case (float32, RGB + depth, no per-pixel counts) runs
//   forward_f4_avx512 on AVX-512 CPUs: the same loop with its masks in mask registers.
// * Backward: per tile, Gaussians back to front from the last contributing one, recomputing
//   T in front by division (3DGS), each in only the rows where the forward blended one of its
//   pixels (rows_hit: a 16-bit row mask per pair that the forward writes; a pair without one
//   is skipped whole), four rows per step. Per-lane gradient sums stay in vector registers over the
//   rows of one Gaussian and are reduced across lanes once per (tile, Gaussian) pair, into
//   that pair's own gradient row (row k for pair k: tiles write disjoint rows, in sequence,
//   so threads never share an accumulator). splat2_reduce sums the rows of each Gaussian in a
//   fixed order (its slots, numbered by splat2_bin_scatter, give its pairs: slot_pair): the
//   gradient does not depend on the thread count or on the scheduling at all (stronger than
//   per-thread [N] buffers, whose sum depends on which thread took which tile).
// * Binning: depth order by a stable LSD radix sort of the float keys (splat2_depth_order),
//   tile lists by a counting sort over fixed chunks in parallel (splat2_bin_count / _scatter).
// * AVX2 / SSE2 builds (no register holds the 64-byte vector): GCC 12 scalarises comparisons
//   and ?: selects on it (per lane a scalar compare or blend with stack stores and reloads), and
//   a 64-byte value returned or assigned as a whole goes through a temporary copied in 8- and
//   16-byte pieces through general registers (then read back as 32 bytes: store-forwarding
//   stalls). That made the AVX2 blend 7-10x slower than the AVX-512 one and no faster than
//   SSE2. The blend's compares and selects go through vlt / vle / vge / vsel and the *_to forms
//   (vlt_to, vsel_to, vsel2_to, vfma_to: into a destination in memory), which in these builds
//   work on the native-width parts (two ymm, four xmm) and write each part straight into the
//   destination; the row masks' any-lane tests OR them part by part (any_lane_of), and the
//   backward's per-row flag is and-ed in rather than selected with ?:. With AVX-512 the helpers
//   are macros for the plain expressions, and where the part-wise form needs a different
//   statement sequence the AVX-512 one is kept under #if: the AVX-512 code is unchanged
//   instruction for instruction. The same per-lane operations: results bit-identical to before
//   at every level. CPU ms, one thread, blend fwd / bwd, Zen 4 with forced levels: 100k
//   Gaussians 512x512 AVX2 300 / 330 -> 40 / 66, SSE2 315 / 366 -> 82 / 121 (AVX-512 27 / 48);
//   fern-cell checkpoint (206k Gaussians, 497x372) AVX2 426 / 467 -> 66 / 112, SSE2 459 / 536
//   -> 131 / 194 (AVX-512 43 / 74). (Taking the AVX2 forward's rows two rather than four per
//   step, or its one-row tail through the row step, measured no different.)
// * exp: float32 uses a Cephes-style polynomial (max relative error ~2 ulp against expf) so
//   that it vectorises; float64 calls std::exp per lane (bit-identical to the scalar kernel's
//   forward, which keeps the float64 parity tests at 1e-9).
//
// Layout: pixel (row i, col j) has centre (j + 0.5, i + 0.5). Tile t = ty * tiles_x + tx covers
// pixels [16 tx, 16 tx + 16) x [16 ty, 16 ty + 16). Pairs [offsets[t], offsets[t+1]) hold the
// Gaussians of tile t in front-to-back order (gauss[k] indexes the N-sized arrays).

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <type_traits>
#include <utility>
#if defined(__AVX2__) || defined(__AVX512F__)
#include <immintrin.h>
#elif defined(__SSE2__)
#include <emmintrin.h>
#endif

#include "vec8d.h"

namespace {

constexpr int TILE = 16;
constexpr int MAXF = 16;  // feature channels handled in registers; more -> caller splits

template <typename T> struct Vec;
template <> struct Vec<float> {
  typedef float v __attribute__((vector_size(64)));
  typedef int32_t m __attribute__((vector_size(64)));
  typedef int32_t mi;
};
template <> struct Vec<double> {
  typedef double v __attribute__((vector_size(128)));
  typedef int64_t m __attribute__((vector_size(128)));
  typedef int64_t mi;
};

template <typename T>
struct Consts {
  static constexpr T alpha_max = T(0.99);
  static constexpr T alpha_min = T(1.0 / 255.0);
  static constexpr T t_min = T(1e-4);
};

// Broadcast a scalar to all 16 lanes. Written as an initialiser list: element-wise stores
// (r[l] = x) compile to 16 masked broadcasts with GCC and made the blend loop 3x slower.
template <typename V> struct Elem;
template <> struct Elem<Vec<float>::v> { typedef float type; };
template <> struct Elem<Vec<float>::m> { typedef int32_t type; };
template <> struct Elem<Vec<double>::v> { typedef double type; };
template <> struct Elem<Vec<double>::m> { typedef int64_t type; };
template <typename V, typename E> inline V splat(E x0) {
  const typename Elem<V>::type x = static_cast<typename Elem<V>::type>(x0);
  return V{x, x, x, x, x, x, x, x, x, x, x, x, x, x, x, x};
}

// Lane-wise comparisons and selects: vlt/vle/vge(a, b) = a < b, <=, >= (a mask), vsel(m, a, b)
// = m ? a : b. With AVX-512 these are the plain vector-extension expressions (one zmm each). In
// the AVX2 and SSE2 builds, where no register holds the 64-byte vector, GCC 12 scalarises
// comparisons and ?: on it (16 scalar compares / blends with stack stores and reloads per
// statement; the AVX2 blend ran 7-10x slower than the AVX-512 one); written on its native-width
// parts (two ymm, four xmm) through a union, each part is one vcmpps / vblendvps (cmpps and
// and/andnot/or with SSE2). The same per-lane results.
#if defined(__AVX512F__)
#define SPLAT_NATIVE_BYTES 64
#elif defined(__AVX__)
#define SPLAT_NATIVE_BYTES 32
#else
#define SPLAT_NATIVE_BYTES 16
#endif
template <typename X> struct MaskOf;
template <> struct MaskOf<Vec<float>::v> { typedef Vec<float>::m type; };
template <> struct MaskOf<Vec<float>::m> { typedef Vec<float>::m type; };
template <> struct MaskOf<Vec<double>::v> { typedef Vec<double>::m type; };
template <> struct MaskOf<Vec<double>::m> { typedef Vec<double>::m type; };
#if SPLAT_NATIVE_BYTES == 64
// (macros: the very expressions the kernel used before, so the AVX-512 code is unchanged)
#define vlt(a, b) ((a) < (b))
#define vle(a, b) ((a) <= (b))
#define vge(a, b) ((a) >= (b))
#define vsel(m, a, b) ((m) ? (a) : (b))
#else
template <typename X> struct Parts {
  typedef typename Elem<X>::type E;
  typedef E p __attribute__((vector_size(SPLAT_NATIVE_BYTES)));
  static constexpr int n = sizeof(X) / SPLAT_NATIVE_BYTES;
  union U {
    X x;
    p part[n];
  };
};
#define SPLAT_CMP(name, op)                                                  \
  template <typename X> inline typename MaskOf<X>::type name(X a, X b) { \
    typedef typename MaskOf<X>::type M;                                    \
    typename Parts<X>::U ua{a}, ub{b};                                     \
    typename Parts<M>::U r;                                                \
    for (int h = 0; h < Parts<X>::n; ++h) r.part[h] = ua.part[h] op ub.part[h]; \
    return r.x;                                                            \
  }
template <typename M, typename X> inline X vsel(M m, X a, X b) {
  typename Parts<M>::U um{m};
  typename Parts<X>::U ua{a}, ub{b};
  for (int h = 0; h < Parts<X>::n; ++h) ua.part[h] = um.part[h] ? ua.part[h] : ub.part[h];
  return ua.x;
}
SPLAT_CMP(vlt, <)
SPLAT_CMP(vle, <=)
SPLAT_CMP(vge, >=)
#undef SPLAT_CMP
#endif
// dst += a * b, dst = m ? a : dst on a vector in memory. With AVX-512 the plain statements.
// Otherwise written part by part into dst: the plain forms built the 64-byte result as one
// value first (an XImode temporary) and copied it over in 16-byte pieces through general
// registers (movq / vpinsrq / xmm stores, the hottest instructions of the AVX2 forward).
#if SPLAT_NATIVE_BYTES == 64
#define vfma_to(dst, a, b) ((dst) += (a) * (b))
#define vsel_to(dst, m, a) ((dst) = (m) ? (a) : (dst))
#define vsel2_to(dst, m, a, b) ((dst) = (m) ? (a) : (b))
#define vlt_to(dst, a, b) ((dst) = (a) < (b))
#define vle_to(dst, a, b) ((dst) = (a) <= (b))
#define vge_to(dst, a, b) ((dst) = (a) >= (b))
#else
template <typename X> inline void vfma_to(X& dst, X a, X b) {
  typedef typename Parts<X>::p P __attribute__((may_alias));
  typename Parts<X>::U ua{a}, ub{b};
  P* d = reinterpret_cast<P*>(&dst);
  for (int h = 0; h < Parts<X>::n; ++h) d[h] += ua.part[h] * ub.part[h];
}
template <typename M, typename X> inline void vsel_to(X& dst, M m, X a) {
  typedef typename Parts<X>::p P __attribute__((may_alias));
  typename Parts<M>::U um{m};
  typename Parts<X>::U ua{a};
  P* d = reinterpret_cast<P*>(&dst);
  for (int h = 0; h < Parts<X>::n; ++h) d[h] = um.part[h] ? ua.part[h] : d[h];
}
template <typename M, typename X> inline void vsel2_to(X& dst, M m, X a, X b) {
  typedef typename Parts<X>::p P __attribute__((may_alias));
  typename Parts<M>::U um{m};
  typename Parts<X>::U ua{a}, ub{b};
  P* d = reinterpret_cast<P*>(&dst);
  for (int h = 0; h < Parts<X>::n; ++h) d[h] = um.part[h] ? ua.part[h] : ub.part[h];
}
#define SPLAT_CMP_TO(name, op)                                                              \
  template <typename X> inline void name(typename MaskOf<X>::type& dst, X a, X b) {         \
    typedef typename MaskOf<X>::type M;                                                     \
    typedef typename Parts<M>::p Q __attribute__((may_alias));                              \
    typename Parts<X>::U ua{a}, ub{b};                                                      \
    Q* d = reinterpret_cast<Q*>(&dst);                                                      \
    for (int h = 0; h < Parts<X>::n; ++h) d[h] = ua.part[h] op ub.part[h];                  \
  }
SPLAT_CMP_TO(vlt_to, <)
SPLAT_CMP_TO(vle_to, <=)
SPLAT_CMP_TO(vge_to, >=)
#undef SPLAT_CMP_TO
#endif

// Lane reductions of a comparison mask (all bits of a lane set or clear).
template <typename M> inline bool any_lane(M m) {
  int64_t r = 0;
  for (int l = 0; l < TILE; ++l) r |= m[l];
  return r != 0;
}
template <typename M> inline bool all_lanes(M m) {
  int64_t r = -1;
  for (int l = 0; l < TILE; ++l) r &= m[l];
  return r != 0;
}
#if defined(__AVX512F__)
template <> inline bool any_lane(Vec<float>::m m) {
  __m512i v;
  std::memcpy(&v, &m, 64);
  return _mm512_test_epi32_mask(v, v) != 0;
}
template <> inline bool all_lanes(Vec<float>::m m) {
  __m512i v;
  std::memcpy(&v, &m, 64);
  return _mm512_test_epi32_mask(v, v) == 0xFFFF;
}
#elif defined(__AVX2__)
template <> inline bool any_lane(Vec<float>::m m) {
  __m256i v[2];
  std::memcpy(v, &m, 64);
  return !_mm256_testz_si256(_mm256_or_si256(v[0], v[1]), _mm256_set1_epi32(-1));
}
template <> inline bool all_lanes(Vec<float>::m m) {
  __m256i v[2];
  std::memcpy(v, &m, 64);
  return _mm256_testc_si256(_mm256_and_si256(v[0], v[1]), _mm256_set1_epi32(-1));
}
#endif
#if SPLAT_NATIVE_BYTES != 64
// any_lane(m[0] | ... | m[n - 1]) for masks in memory, OR-ed part by part: the OR of whole
// 64-byte masks, passed on as one value, was copied in pieces and read back at once (a
// store-forwarding stall in every row step of the AVX2 forward, ~12% of it).
template <typename M> inline bool any_lane_of(const M* m, int n) {
  typedef typename Parts<M>::p Q __attribute__((may_alias));
  constexpr int NP = Parts<M>::n;
  const Q* q = reinterpret_cast<const Q*>(m);
  Q acc = q[0];
  for (int h = 1; h < n * NP; ++h) acc |= q[h];
#if defined(__AVX2__)
  __m256i v;
  std::memcpy(&v, &acc, sizeof(v));
  return !_mm256_testz_si256(v, v);
#elif defined(__SSE2__)
  __m128i v;
  std::memcpy(&v, &acc, sizeof(v));
  return _mm_movemask_epi8(v) != 0;
#else
  int64_t r = 0;
  for (int l = 0; l < (int)(sizeof(Q) / sizeof(acc[0])); ++l) r |= acc[l];
  return r != 0;
#endif
}
#endif
template <typename T> inline T hsum(typename Vec<T>::v v) {
  // Fixed pairwise tree: the same order on every machine and vector width.
  T s[TILE];
  for (int l = 0; l < TILE; ++l) s[l] = v[l];
  for (int w = TILE / 2; w > 0; w /= 2)
    for (int l = 0; l < w; ++l) s[l] += s[l + w];
  return s[0];
}
#if defined(__AVX2__) || defined(__AVX512F__)
// The same tree in registers (lane l + lane l + w for w = 8, 4, 2, 1; float addition commutes,
// so the sums are bit-identical): the generic version went through a stack array, ~9 of them
// per (tile, Gaussian) pair in the backward.
template <> inline float hsum<float>(Vec<float>::v v) {
  __m256 h[2];
  std::memcpy(h, &v, 64);
  const __m256 s8 = _mm256_add_ps(h[0], h[1]);
  const __m128 s4 = _mm_add_ps(_mm256_castps256_ps128(s8), _mm256_extractf128_ps(s8, 1));
  const __m128 s2 = _mm_add_ps(s4, _mm_movehl_ps(s4, s4));
  const __m128 s1 = _mm_add_ss(s2, _mm_shuffle_ps(s2, s2, 1));
  return _mm_cvtss_f32(s1);
}
#endif

// hsum of 8 vectors at once: out[j] = hsum(v[j]) with the very same additions (lane l + lane
// l + w for w = 8, 4, 2, 1), done for 8 vectors together by shuffles that pair their halves:
// 26 instructions where 8 separate sums take ~64. The backward's per-(tile, Gaussian) lane
// sums (6 + 3 of them) were ~10% of its time.
#if defined(__AVX512F__)
inline void hsum8(const Vec<float>::v* v, float* out) {
  __m512 x[8];
  std::memcpy(x, v, sizeof(x));
  __m512 u[4], r[2];
  for (int j = 0; j < 4; ++j)  // w = 8: [v_2j lanes 0-7 | v_2j+1 lanes 0-7] (each lane l + l + 8)
    u[j] = _mm512_add_ps(_mm512_shuffle_f32x4(x[2 * j], x[2 * j + 1], 0x44),
                         _mm512_shuffle_f32x4(x[2 * j], x[2 * j + 1], 0xEE));
  for (int j = 0; j < 2; ++j)  // w = 4: 128-bit lane k holds v_4j+k's lanes 0-3
    r[j] = _mm512_add_ps(_mm512_shuffle_f32x4(u[2 * j], u[2 * j + 1], 0x88),
                         _mm512_shuffle_f32x4(u[2 * j], u[2 * j + 1], 0xDD));
  // w = 2: lane k holds (v_k 0-1, v_k+4 0-1); w = 1: (v_k, v_k+4, v_k, v_k+4)
  const __m512 t = _mm512_add_ps(_mm512_shuffle_ps(r[0], r[1], 0x44), _mm512_shuffle_ps(r[0], r[1], 0xEE));
  const __m512 s = _mm512_add_ps(_mm512_shuffle_ps(t, t, 0x88), _mm512_shuffle_ps(t, t, 0xDD));
  // lanes 4k, 4k + 1 are v_k, v_k+4: gather v_0 .. v_7 into lanes 0 .. 7
  const __m512i idx = _mm512_setr_epi32(0, 4, 8, 12, 1, 5, 9, 13, 0, 0, 0, 0, 0, 0, 0, 0);
  _mm256_storeu_ps(out, _mm512_castps512_ps256(_mm512_permutexvar_ps(idx, s)));
}
#endif

// exp for power <= 0 (callers mask out the rest). float: Cephes expf polynomial on
// x = n ln2 + r, |r| <= ln2 / 2, scaled by 2^n through the exponent bits; below -20 -> 0.
// With AVX-512 (vexpn): x clamped at -20 by one max and the scaling by one vscalefps (exact,
// as the exponent-bit product is, for these normal results), where the other builds compare,
// select, convert, add, shift, multiply and select: ~19 -> ~14 operations per vector; below
// -20 it returns e^-20 (~2e-9). Either way the value below -20 is one no caller can see:
// alpha = opacity e^x < 1/255 there, so the blending rules skip the lane (images and gradients
// bit-identical to exact e^x). The cut was -87 (where expf underflows): e^x times an opacity
// was then a subnormal float in some lanes, and subnormal arithmetic (most lanes of a small
// Gaussian's row are far out) cost the blend 7-20%. Fern checkpoint, one thread, CPU ms, fwd /
// bwd: AVX-512 44 / 75 -> 40 / 70 (clamping the AVX-512 form at -87 instead: 53 / 83);
// AVX2 67 / 106 -> 61 / 98.
// The steps every exp form shares: n = round(x / ln 2) (by the 1.5 * 2^23 magic number),
// r = x - n ln 2 (ln 2 in two parts), p = the Cephes polynomial, ~e^r; e^x = p 2^n.
template <int NQ> inline void exp_reduce(const Vec<float>::v* x, Vec<float>::v* n, Vec<float>::v* p) {
  typedef Vec<float>::v V;
  V r[NQ];
  const V magic = splat<V>(12582912.0f);
  for (int q = 0; q < NQ; ++q) n[q] = (x[q] * splat<V>(1.44269504088896341f) + magic) - magic;
  for (int q = 0; q < NQ; ++q) r[q] = x[q] - n[q] * splat<V>(0.693359375f);
  for (int q = 0; q < NQ; ++q) r[q] = r[q] - n[q] * splat<V>(-2.12194440e-4f);
  for (int q = 0; q < NQ; ++q) p[q] = splat<V>(1.9875691500e-4f);
  for (int q = 0; q < NQ; ++q) p[q] = p[q] * r[q] + splat<V>(1.3981999507e-3f);
  for (int q = 0; q < NQ; ++q) p[q] = p[q] * r[q] + splat<V>(8.3334519073e-3f);
  for (int q = 0; q < NQ; ++q) p[q] = p[q] * r[q] + splat<V>(4.1665795894e-2f);
  for (int q = 0; q < NQ; ++q) p[q] = p[q] * r[q] + splat<V>(1.6666665459e-1f);
  for (int q = 0; q < NQ; ++q) p[q] = p[q] * r[q] + splat<V>(5.0000001201e-1f);
  for (int q = 0; q < NQ; ++q) p[q] = p[q] * r[q] * r[q] + r[q] + splat<V>(1.0f);
}
template <int NQ> inline void vexpn(Vec<float>::v* x);
inline Vec<float>::v vexp(Vec<float>::v x) {
  vexpn<1>(&x);
  return x;
}
// vexp of NQ vectors with the steps interleaved (independent dependency chains in program
// order: the blend loops take several tile rows per step, see forward_impl). Per lane as vexp.
template <int NQ> inline void vexpn(Vec<float>::v* x) {
  typedef Vec<float>::v V;
#if defined(__AVX512F__)
  {
    V n[NQ], p[NQ];
    for (int q = 0; q < NQ; ++q) {
      __m512 xv;
      std::memcpy(&xv, &x[q], 64);
      xv = _mm512_max_ps(xv, _mm512_set1_ps(-20.0f));
      std::memcpy(&x[q], &xv, 64);
    }
    exp_reduce<NQ>(x, n, p);
    for (int q = 0; q < NQ; ++q) {
      __m512 pv, nv;
      std::memcpy(&pv, &p[q], 64);
      std::memcpy(&nv, &n[q], 64);
      pv = _mm512_scalef_ps(pv, nv);
      std::memcpy(&x[q], &pv, 64);
    }
    return;
  }
#endif
  typedef Vec<float>::m M;
  M tiny[NQ];
  V n[NQ], p[NQ];
  M ni[NQ], bits[NQ];
  for (int q = 0; q < NQ; ++q) vlt_to(tiny[q], x[q], splat<V>(-20.0f));
  for (int q = 0; q < NQ; ++q) vsel_to(x[q], tiny[q], splat<V>(-20.0f));
  exp_reduce<NQ>(x, n, p);
  for (int q = 0; q < NQ; ++q) ni[q] = __builtin_convertvector(n[q], M);
  for (int q = 0; q < NQ; ++q) bits[q] = (ni[q] + 127) << 23;
  for (int q = 0; q < NQ; ++q) {
    V scale;
    std::memcpy(&scale, &bits[q], sizeof(V));
    const V res = p[q] * scale;
    vsel2_to(x[q], tiny[q], splat<V>(0.0f), res);
  }
}
inline void vexp2(Vec<float>::v* x) { vexpn<2>(x); }
inline Vec<double>::v vexp(Vec<double>::v x);
template <int NQ> inline void vexpn(Vec<double>::v* x) {
  for (int q = 0; q < NQ; ++q) x[q] = vexp(x[q]);
}
inline void vexp2(Vec<double>::v* x) { vexpn<2>(x); }
inline Vec<double>::v vexp(Vec<double>::v x) {
  Vec<double>::v r;
  for (int l = 0; l < TILE; ++l) r[l] = std::exp(x[l]);
  return r;
}

// 1 / x for x in [0.01, 1] (1 - alpha). float with AVX-512: the 14-bit estimate and one
// Newton step (~2^-28 relative, within an ulp or two of the division, at a fraction of its
// cost); float64 and other builds divide.
inline Vec<float>::v recip(Vec<float>::v x) {
#if defined(__AVX512F__)
  __m512 xv, r;
  std::memcpy(&xv, &x, 64);
  r = _mm512_maskz_rcp14_ps(0xFFFF, xv);  // (the unmasked form trips -Wmaybe-uninitialized in GCC 12's header)
  r = _mm512_mul_ps(r, _mm512_fnmadd_ps(xv, r, _mm512_set1_ps(2.0f)));
  Vec<float>::v out;
  std::memcpy(&out, &r, 64);
  return out;
#else
  return splat<Vec<float>::v>(1.0f) / x;
#endif
}
inline Vec<double>::v recip(Vec<double>::v x) { return splat<Vec<double>::v>(1.0) / x; }

// Where a Gaussian can reach alpha >= 1/255 inside a tile: the ellipse q = d^T conic d <= r2 =
// 2 ln(255 op) (+1% + 1e-3 margin; the scalar kernel's footprint rule). Computed once per
// Gaussian (splat2_footprint: a log, a sqrt and divisions that would otherwise run per tile
// pair) as one 64-byte record fp[FP * g ..] = (half, b / a, r2 / a, det / a^2, mx, my, dy*, 0),
// used by
// row_range(): tile-local rows [i0, i1) with |dy| <= half = sqrt(r2 a / det) (+1e-3), the rows
// the forward visits;
// binning (for_tiles, from a separate int16 record): the tile rectangle of the ellipse's
// bounding box (within the 3-sigma rectangle), and per tile row the span of tiles where the
// slice test can hold (tile_spans; dy* is the row offset of the ellipse's rightmost point).
// The slice test: the ellipse's slice at a row centre (centre x = mx + b dy / a, half-width
// sqrt(r2 / a - dy^2 det / a^2)) comes within one pixel of the tile's pixel centres.
// All only skip work whose pixels the blending rules skip anyway. half < 0: opacity below
// 1/255, nothing to blend. Not positive definite (never after the 0.3 dilation): every row
// and column (half = r2 / a = 1e300).
constexpr int FP = 8;

// The tile rectangle [x0, x1) x [y0, y1) of the tiles that hold a pixel centre within one
// pixel (the blend's margin, plus slack for rounding) of the footprint's bounding box:
// rows |dy| <= half + 1e-3 (the float32 rounding of dy in the blend), x within the widest
// slice sqrt(r2 / a (1 + b^2 / (a c - b^2))) of the centre, clipped to the 3-sigma rectangle r.
inline void bbox_tiles(const double* fp, const int64_t* r, int64_t* out) {
  for (int k = 0; k < 4; ++k) out[k] = r[k];
  if (fp[0] < 0) { out[1] = out[0]; out[3] = out[2]; return; }
  if (!(fp[0] < 1e299)) return;
  const double mx = fp[4], my = fp[5], b1 = fp[1], f2 = fp[2], f3 = fp[3];
  const double X = std::sqrt(f2 * (f3 + b1 * b1) / f3);
  const double slack = 1.0 + 1e-3 + 2e-3 * std::fabs(b1) + 1e-6 * (std::fabs(mx) + X);
  const double ys = fp[0] + 1e-3 + 1e-6 * std::fabs(my);
  const double t[4] = {std::ceil((mx - X - slack - (TILE - 0.5)) / TILE), std::floor((mx + X + slack - 0.5) / TILE) + 1,
                       std::ceil((my - ys - (TILE - 0.5)) / TILE), std::floor((my + ys - 0.5) / TILE) + 1};
  for (int k = 0; k < 4; ++k)
    if (std::isnan(t[k])) return;
  for (int k = 0; k < 4; k += 2) {
    if (t[k] > (double)out[k]) out[k] = t[k] >= (double)out[k + 1] ? out[k + 1] : (int64_t)t[k];
    if (t[k + 1] < (double)out[k + 1]) out[k + 1] = t[k + 1] <= (double)out[k] ? out[k] : (int64_t)t[k + 1];
  }
  if (out[1] <= out[0] || out[3] <= out[2]) { out[1] = out[0]; out[3] = out[2]; }
}

template <typename Fn> inline void tile_spans(const double* fp, const int64_t* r, Fn&& fn);
// Binning record per Gaussian (int16, 64 bytes: one cache line for the depth-ordered passes):
// its tiles (x0, x1, y0, y1), then the column span (c0, c1) of each of its first SPAN_ROWS tile
// rows (all of them when the box is at most SPAN_ROWS rows tall).
constexpr int SPAN_ROWS = 14;
constexpr int SPREC = 4 + 2 * SPAN_ROWS;
inline bool use_spans(const double* fp, const int64_t* r) {
  return r[1] - r[0] >= 2 && r[3] - r[2] >= 2 && fp[0] < 1e299;
}

template <typename T>
inline void footprint(T a, T b, T c, T op, T mx, T my, const int64_t* rect, double* fp, int16_t* spans) {
  fp[4] = mx; fp[5] = my; fp[6] = 0; fp[7] = 0;
  if (op < Consts<T>::alpha_min) {
    fp[0] = -1; fp[1] = fp[2] = fp[3] = 0;
  } else if (!((a > 0) && (c > 0) && (a * c - b * b > 0))) {
    fp[0] = fp[2] = 1e300; fp[1] = fp[3] = 0;
  } else {
    const double lim = std::max(255.0 * (double)op, 1.0);
    const double r2 = (double)(T)(2.0 * std::log(lim) * 1.01 + 1e-3);
    const double da = a, db = b, dc = c;
    const double det_a = (da * dc - db * db) / da;
    fp[0] = std::sqrt(r2 / det_a) + 1e-3;
    fp[1] = db / da;
    fp[2] = r2 / da;
    fp[3] = det_a / da;
    // tangent point of the rightmost slice end: d/ddy (b1 dy + sqrt(f2 - f3 dy^2)) = 0
    fp[6] = fp[1] * std::sqrt(fp[2] / (fp[3] * (fp[3] + fp[1] * fp[1])));
  }
  if (rect && spans) {
    int64_t t[4];
    bbox_tiles(fp, rect, t);
    for (int k = 0; k < 4; ++k) spans[k] = (int16_t)t[k];
    if (t[3] - t[2] <= SPAN_ROWS) {
      if (use_spans(fp, t)) {
        tile_spans(fp, t, [&](int64_t y, int64_t c0, int64_t c1) {
          spans[4 + 2 * (y - t[2])] = (int16_t)c0;
          spans[5 + 2 * (y - t[2])] = (int16_t)c1;
        });
      } else {
        for (int64_t y = t[2]; y < t[3]; ++y) {
          spans[4 + 2 * (y - t[2])] = (int16_t)t[0];
          spans[5 + 2 * (y - t[2])] = (int16_t)t[1];
        }
      }
    }
  }
}

inline void row_range(const double* fp, double my, double py0, int rows, int& i0, int& i1) {
  double lo = std::ceil(my - fp[0] - py0 - 0.5);
  double hi = std::floor(my + fp[0] - py0 - 0.5);
  lo = std::max(lo, 0.0);
  hi = std::min(hi, double(rows - 1));
  if (!(lo <= hi)) { i0 = 0; i1 = 0; return; }
  i0 = (int)lo;
  i1 = (int)hi + 1;
}

// fn(ty, c0, c1) for each tile row ty of the rectangle r = (x0, x1, y0, y1): the tile columns
// [c0, c1) within r where the slice test (see FP) can hold for a row that row_range() visits.
// A superset,
// so binning only these pairs changes no pixel and no gradient (the dropped pairs would blend
// nothing). The row offsets dy = my - y of tile row ty's pixel centres lie in the band
// [my - 16 (ty + 1), my - 16 ty] (half a pixel of slack each side, more than the float32
// rounding of dy in the blend), clipped to |dy| <= half + 1e-3. Over a band the slice's right
// end xc + hw = mx + fp1 dy + sqrt(fp2 - fp3 dy^2) is concave where the root is real and
// linear (fp1 dy, hw clamped to 0) outside: its maximum is at the tangent point dy* if the band
// holds it, else at an end of the band; the left end likewise (at -dy*). Adjacent bands share
// their ends, so each end's root is taken once. Then one pixel (the blend's margin) plus a
// relative 1e-6 of slack; a tile is kept when the x range reaches its pixel centres.
template <typename Fn>
inline void tile_spans(const double* fp, const int64_t* r, Fn&& fn) {
  const double mx = fp[4], my = fp[5], b1 = fp[1], f2 = fp[2], f3 = fp[3], dstar = fp[6];
  const double H = fp[0] + 1e-3;
  const double slack = 1.0 + 1e-3 + 1e-6 * (std::fabs(mx) + std::fabs(b1) * H + std::sqrt(f2));
  auto hw = [&](double d) { return std::sqrt(std::max(f2 - d * d * f3, 0.0)); };
  double e1 = std::min(std::max(my - (double)(r[2] * TILE), -H), H);  // band top end (larger dy)
  double h1 = hw(e1);
  for (int64_t y = r[2]; y < r[3]; ++y) {
    const double e0 = std::min(std::max(my - (double)((y + 1) * TILE), -H), H);
    const double h0 = hw(e0);
    double xr = std::max(b1 * e0 + h0, b1 * e1 + h1);
    double xl = std::min(b1 * e0 - h0, b1 * e1 - h1);
    if (dstar > e0 && dstar < e1) xr = std::max(xr, b1 * dstar + hw(dstar));
    if (-dstar > e0 && -dstar < e1) xl = std::min(xl, -b1 * dstar - hw(dstar));
    e1 = e0;
    h1 = h0;
    int64_t c0 = r[0], c1 = r[1];
    // tile tx is hit when xmax >= 16 tx + 0.5 and xmin <= 16 tx + 15.5
    const double t0 = std::ceil((mx + xl - slack - (TILE - 0.5)) / TILE);
    const double t1 = std::floor((mx + xr + slack - 0.5) / TILE) + 1;
    if (!(t0 < t1)) {
      if (!std::isnan(t0) && !std::isnan(t1)) c1 = c0;
    } else {
      if (t0 > (double)c0) c0 = t0 >= (double)c1 ? c1 : (int64_t)t0;
      if (t1 < (double)c1) c1 = t1 <= (double)c0 ? c0 : (int64_t)t1;
    }
    fn(y, c0, c1);
  }
}

// footprint() with its binning record for 8 Gaussians at once, one per double lane (the
// footprint pass is per Gaussian and was scalar, branchy double code: ~10 ms of a 100k
// Gaussian, 512x512 forward; the scalar footprint() stays as the reference it must match,
// splat2_footprint_scalar_*). Each lane computes what footprint() computes (the same double
// expressions; branches become per-lane selects, the opacity and definiteness tests and the
// log stay per lane in T); tile_spans() runs over the rows of the tallest lane with its per-row
// state in lanes. Lanes l >= nl are padding (copies of the first Gaussian), never written.
namespace fpv {
using namespace vec8d;  // D, Mk, LN, bc, vmax, vmin, vsqrt, vfloor, vceil
inline D vabs(D x) { return x < bc(0.0) ? -x : x; }
inline Mk isnan(D x) { return x != x; }

// Clip [t_lo, t_hi) (doubles, maybe NaN) into [lo, hi) as bbox_tiles() and tile_spans() do.
inline void clip(D t_lo, D t_hi, D& lo, D& hi) {
  lo = t_lo > lo ? (t_lo >= hi ? hi : t_lo) : lo;
  hi = t_hi < hi ? (t_hi <= lo ? lo : t_hi) : hi;
}

template <typename T>
void footprint_block(int64_t g0, int nl, const T* co, const T* op, const T* mu, const int64_t* rect,
                     double* fps, int16_t* sps) {
  D a, b, c, mx, my, r2;
  Mk low, npd;  // opacity below 1/255; not positive definite
  for (int l = 0; l < LN; ++l) {
    const int64_t g = g0 + (l < nl ? l : 0);
    const T ta = co[3 * g], tb = co[3 * g + 1], tc = co[3 * g + 2], to = op[g];
    a[l] = ta; b[l] = tb; c[l] = tc;
    mx[l] = mu[2 * g]; my[l] = mu[2 * g + 1];
    low[l] = to < Consts<T>::alpha_min ? -1 : 0;
    npd[l] = !low[l] && !((ta > 0) && (tc > 0) && (ta * tc - tb * tb > 0)) ? -1 : 0;
    const double lim = std::max(255.0 * (double)to, 1.0);
    r2[l] = (low[l] || npd[l]) ? 1.0 : (double)(T)(2.0 * std::log(lim) * 1.01 + 1e-3);
  }
  const Mk pd = ~(low | npd);
  const D det_a = (a * c - b * b) / a;
  const D f0v = vsqrt(r2 / det_a) + 1e-3, f1v = b / a, f2v = r2 / a, f3v = det_a / a;
  const D f6v = f1v * vsqrt(f2v / (f3v * (f3v + f1v * f1v)));
  const D zero = bc(0.0);
  const D f[8] = {pd ? f0v : (low ? bc(-1.0) : bc(1e300)), pd ? f1v : zero,
                  pd ? f2v : (low ? zero : bc(1e300)), pd ? f3v : zero, mx, my, pd ? f6v : zero, zero};
  for (int l = 0; l < nl; ++l)
    for (int k = 0; k < FP; ++k) fps[FP * (g0 + l) + k] = f[k][l];
  if (!rect || !sps) return;
  // bbox_tiles()
  D t[4];
  for (int l = 0; l < LN; ++l)
    for (int k = 0; k < 4; ++k) t[k][l] = (double)rect[4 * (g0 + (l < nl ? l : 0)) + k];
  const Mk finite = f[0] < bc(1e299);  // false for the 1e300 of npd lanes (and inf, NaN)
  {
    const D b1 = f[1], f2 = f[2], f3 = f[3];
    const D X = vsqrt(f2 * (f3 + b1 * b1) / f3);
    const D slack = 1.0 + 1e-3 + 2e-3 * vabs(b1) + 1e-6 * (vabs(mx) + X);
    const D ys = f[0] + 1e-3 + 1e-6 * vabs(my);
    const D tt[4] = {vceil((mx - X - slack - (TILE - 0.5)) / TILE), vfloor((mx + X + slack - 0.5) / TILE) + 1,
                     vceil((my - ys - (TILE - 0.5)) / TILE), vfloor((my + ys - 0.5) / TILE) + 1};
    const Mk use = ~low & finite & ~(isnan(tt[0]) | isnan(tt[1]) | isnan(tt[2]) | isnan(tt[3]));
    D o[4] = {t[0], t[1], t[2], t[3]};
    clip(tt[0], tt[1], o[0], o[1]);
    clip(tt[2], tt[3], o[2], o[3]);
    const Mk empty = (o[1] <= o[0]) | (o[3] <= o[2]);
    o[1] = empty ? o[0] : o[1];
    o[3] = empty ? o[2] : o[3];
    for (int k = 0; k < 4; ++k) t[k] = use ? o[k] : t[k];
    t[1] = low ? t[0] : t[1];
    t[3] = low ? t[2] : t[3];
  }
  const D rows = t[3] - t[2];
  const Mk spans_on = finite & (t[1] - t[0] >= 2.0) & (rows >= 2.0) & (rows <= (double)SPAN_ROWS);
  int max_rows = 0;
  for (int l = 0; l < nl; ++l) {
    int16_t* sp = sps + SPREC * (g0 + l);
    for (int k = 0; k < 4; ++k) sp[k] = (int16_t)t[k][l];
    if (rows[l] <= SPAN_ROWS) {
      if (spans_on[l]) {
        max_rows = std::max(max_rows, (int)rows[l]);
      } else {
        for (int y = 0; y < (int)rows[l]; ++y) {
          sp[4 + 2 * y] = (int16_t)t[0][l];
          sp[5 + 2 * y] = (int16_t)t[1][l];
        }
      }
    }
  }
  if (max_rows == 0) return;
  // tile_spans() over the rows of the tallest lane
  const D b1 = f[1], f2 = f[2], f3 = f[3], dstar = f[6];
  const D H = f[0] + 1e-3;
  const D slack = 1.0 + 1e-3 + 1e-6 * (vabs(mx) + vabs(b1) * H + vsqrt(f2));
  auto hw = [&](D d) { return vsqrt(vmax(f2 - d * d * f3, zero)); };
  const D hstar = hw(dstar);
  D e1 = vmin(vmax(my - t[2] * TILE, -H), H);
  D h1 = hw(e1);
  for (int y = 0; y < max_rows; ++y) {
    const D e0 = vmin(vmax(my - (t[2] + (y + 1)) * TILE, -H), H);
    const D h0 = hw(e0);
    D xr = vmax(b1 * e0 + h0, b1 * e1 + h1);
    D xl = vmin(b1 * e0 - h0, b1 * e1 - h1);
    xr = (dstar > e0) & (dstar < e1) ? vmax(xr, b1 * dstar + hstar) : xr;
    xl = (-dstar > e0) & (-dstar < e1) ? vmin(xl, -b1 * dstar - hstar) : xl;
    e1 = e0;
    h1 = h0;
    D c0 = t[0], c1 = t[1];
    const D t0 = vceil((mx + xl - slack - (TILE - 0.5)) / TILE);
    const D t1 = vfloor((mx + xr + slack - 0.5) / TILE) + 1;
    const Mk ordered = t0 < t1;
    D k0 = c0, k1 = c1;
    clip(t0, t1, k0, k1);
    const Mk collapse = ~ordered & ~isnan(t0) & ~isnan(t1);
    c1 = ordered ? k1 : (collapse ? c0 : c1);
    c0 = ordered ? k0 : c0;
    for (int l = 0; l < nl; ++l) {
      if (!spans_on[l] || y >= (int)rows[l]) continue;
      int16_t* sp = sps + SPREC * (g0 + l);
      sp[4 + 2 * y] = (int16_t)c0[l];
      sp[5 + 2 * y] = (int16_t)c1[l];
    }
  }
}
}  // namespace fpv

// Binning visits Gaussians in depth order, i.e. at random addresses: fetch the rectangle and
// footprint a few Gaussians ahead (the loop over tiles is too branchy for the CPU to overlap
// those misses by itself).
constexpr int64_t PREFETCH = 8;
inline void prefetch_gaussian(const int64_t* rect, const double* fps, const int16_t* sps, int64_t g) {
  if (fps) {
    __builtin_prefetch(sps + SPREC * g);
  } else {
    __builtin_prefetch(rect + 4 * g);
  }
}

// The tiles of one Gaussian, tile rows in order, each row's span left to right: without
// footprints its rectangle r; with them the footprint's bounding-box tiles, and where that has
// two or more rows and columns only each row's span (with one row or one column every tile of
// the box is reached: the ellipse is connected and touches every row and column of its box).
// From the binning record sp when given (taller boxes: their spans computed here from fp).
template <typename Fn>
inline void for_rows(const int64_t* rect, const double* fp, const int16_t* sp, Fn&& fn) {
  int64_t r[4];
  if (!sp) {
    for (int64_t y = rect[2]; y < rect[3]; ++y) fn(y, rect[0], rect[1]);
    return;
  }
  for (int k = 0; k < 4; ++k) r[k] = sp[k];
  if (r[3] - r[2] <= SPAN_ROWS) {
    for (int64_t y = r[2]; y < r[3]; ++y) fn(y, (int64_t)sp[4 + 2 * (y - r[2])], (int64_t)sp[5 + 2 * (y - r[2])]);
  } else if (use_spans(fp, r)) {
    tile_spans(fp, r, fn);
  } else {
    for (int64_t y = r[2]; y < r[3]; ++y) fn(y, r[0], r[1]);
  }
}
// The same tiles one by one (for_rows gives each tile row's span [c0, c1)).
template <typename Fn>
inline void for_tiles(const int64_t* rect, const double* fp, const int16_t* sp, Fn&& fn) {
  for_rows(rect, fp, sp, [&](int64_t y, int64_t c0, int64_t c1) {
    for (int64_t x = c0; x < c1; ++x) fn(y, x);
  });
}

// 16 pixels x 4 interleaved channels (64 floats, pixel-major as in accum [H, W, 4]) <->
// 4 per-channel 16-lane vectors, by two rounds of two-input shuffles (no per-lane moves).
#if defined(__clang__) || (defined(__GNUC__) && __GNUC__ >= 12)
#define SPLAT_SHUFFLE 1
inline void deinterleave4(const float* src, Vec<float>::v* out) {
  typedef Vec<float>::v V;
  V v[4];
  std::memcpy(v, src, sizeof(v));
#define SPLAT_D4(f)                                                                                  \
  {                                                                                                  \
    const V a = __builtin_shufflevector(v[0], v[1], f, f + 4, f + 8, f + 12, f + 16, f + 20, f + 24, \
                                        f + 28, 0, 0, 0, 0, 0, 0, 0, 0);                             \
    const V b = __builtin_shufflevector(v[2], v[3], f, f + 4, f + 8, f + 12, f + 16, f + 20, f + 24, \
                                        f + 28, 0, 0, 0, 0, 0, 0, 0, 0);                             \
    out[f] = __builtin_shufflevector(a, b, 0, 1, 2, 3, 4, 5, 6, 7, 16, 17, 18, 19, 20, 21, 22, 23);  \
  }
  SPLAT_D4(0) SPLAT_D4(1) SPLAT_D4(2) SPLAT_D4(3)
#undef SPLAT_D4
}
inline void interleave4(const Vec<float>::v* in, float* dst) {
  typedef Vec<float>::v V;
  // pixels 0-7 of channels (0, 1) and (2, 3) paired, then the four channels per pixel
  const V lo01 = __builtin_shufflevector(in[0], in[1], 0, 16, 1, 17, 2, 18, 3, 19, 4, 20, 5, 21, 6, 22, 7, 23);
  const V hi01 = __builtin_shufflevector(in[0], in[1], 8, 24, 9, 25, 10, 26, 11, 27, 12, 28, 13, 29, 14, 30, 15, 31);
  const V lo23 = __builtin_shufflevector(in[2], in[3], 0, 16, 1, 17, 2, 18, 3, 19, 4, 20, 5, 21, 6, 22, 7, 23);
  const V hi23 = __builtin_shufflevector(in[2], in[3], 8, 24, 9, 25, 10, 26, 11, 27, 12, 28, 13, 29, 14, 30, 15, 31);
  V o[4];
  o[0] = __builtin_shufflevector(lo01, lo23, 0, 1, 16, 17, 2, 3, 18, 19, 4, 5, 20, 21, 6, 7, 22, 23);
  o[1] = __builtin_shufflevector(lo01, lo23, 8, 9, 24, 25, 10, 11, 26, 27, 12, 13, 28, 29, 14, 15, 30, 31);
  o[2] = __builtin_shufflevector(hi01, hi23, 0, 1, 16, 17, 2, 3, 18, 19, 4, 5, 20, 21, 6, 7, 22, 23);
  o[3] = __builtin_shufflevector(hi01, hi23, 8, 9, 24, 25, 10, 11, 26, 27, 12, 13, 28, 29, 14, 15, 30, 31);
  std::memcpy(dst, o, sizeof(o));
}
#endif

// The blend reads five arrays per tile-Gaussian pair at the Gaussian's index (mean, conic,
// opacity, features, footprint): in depth order these are scattered over ~10 MB at 100k
// Gaussians, so each pair waited on several cache misses. Fetch them PAIR_PREFETCH pairs ahead.
// (4 rather than 2 since the row loop has no per-row branches: a pair now takes fewer cycles;
// fern checkpoint forward ~54 -> ~52 ms CPU.)
constexpr int64_t PAIR_PREFETCH = 4;
template <typename T>
inline void prefetch_pair(int64_t g, const T* means2d, const T* conics, const T* opac, const T* feat, int64_t F,
                          const double* fps) {
  __builtin_prefetch(means2d + 2 * g);
  __builtin_prefetch(conics + 3 * g);
  __builtin_prefetch(opac + g);
  __builtin_prefetch(feat + g * F);
  __builtin_prefetch(fps + FP * g);
}

// One tile-Gaussian pair as the blend loops read it: Gaussian g's mean, conic, opacity,
// features and footprint record. False when its opacity is below 1/255 (it blends nothing).
// The forwards take the pair's rows from row_range(p.fp, ...); the backward from rows_hit.
template <typename T>
struct Pair {
  T mx, my, a, b, c, op;
  const T* fg;
  const double* fp;
};
template <typename T>
inline bool load_pair(int64_t g, const T* means2d, const T* conics, const T* opac, const T* feat, int64_t F,
                      const double* fps, Pair<T>& p) {
  p.mx = means2d[2 * g];
  p.my = means2d[2 * g + 1];
  p.a = conics[3 * g];
  p.b = conics[3 * g + 1];
  p.c = conics[3 * g + 2];
  p.op = opac[g];
  p.fp = fps + FP * g;
  if (p.fp[0] < 0) return false;
  p.fg = feat + g * F;
  return true;
}

// Work item c of the blend loops: tile t (tile_order[c], the busiest first, see Bins), its
// first pixel (x0, y0) and its rows and columns inside the image (fewer than TILE at the right
// and bottom edges).
struct Tile {
  int64_t t, x0, y0;
  int rows, cols;
};
inline Tile tile_at(int64_t c, const int32_t* tile_order, int64_t tiles_x, int64_t W, int64_t H) {
  Tile tl;
  tl.t = tile_order ? tile_order[c] : c;
  tl.x0 = (tl.t % tiles_x) * TILE;
  tl.y0 = (tl.t / tiles_x) * TILE;
  tl.rows = (int)std::min<int64_t>(TILE, H - tl.y0);
  tl.cols = (int)std::min<int64_t>(TILE, W - tl.x0);
  return tl;
}

// Row i of a finished forward tile into the outputs: T, the last contributor, the blend count
// (when count is given) and the F channels of the accumulators (FS vectors per row).
template <typename T, int64_t FS>
inline void store_tile_row(const Tile& tl, int i, int64_t W, int64_t F, const typename Vec<T>::v* Tr,
                           const typename Vec<T>::m* last, const typename Vec<T>::m* count,
                           const typename Vec<T>::v* acc, T* out_accum, T* out_T, int32_t* out_last,
                           int32_t* out_count) {
  typedef typename Vec<T>::v V;
  typedef typename Vec<T>::m M;
  const int64_t row = (tl.y0 + i) * W + tl.x0;
  const int cols = tl.cols;
  if (sizeof(T) == 4 && cols == TILE) {  // a full row: three plain 64-byte copies
    std::memcpy(out_T + row, &Tr[i], sizeof(V));
    std::memcpy(out_last + row, &last[i], sizeof(M));
    if (count) std::memcpy(out_count + row, &count[i], sizeof(M));
#ifdef SPLAT_SHUFFLE
    if (F == 4) {
      interleave4(reinterpret_cast<const Vec<float>::v*>(&acc[i * FS]), reinterpret_cast<float*>(out_accum + row * 4));
      return;
    }
#endif
    for (int j = 0; j < cols; ++j)
      for (int64_t f = 0; f < F; ++f) out_accum[(row + j) * F + f] = acc[i * FS + f][j];
    return;
  }
  for (int j = 0; j < cols; ++j) {
    out_T[row + j] = Tr[i][j];
    out_last[row + j] = (int32_t)last[i][j];
    if (count) out_count[row + j] = (int32_t)count[i][j];
    for (int64_t f = 0; f < F; ++f) out_accum[(row + j) * F + f] = acc[i * FS + f][j];
  }
}

// FC > 0: F == FC as a compile-time constant (4: RGB + depth, the rasterizer's case).
// CNT: out_count is wanted (the per-pixel blend counts; benchmarks and tests): the
// rasterizer passes none, which saves two of the ~40 vector operations per row.
template <typename T, int FC, bool CNT>
void forward_impl(int64_t tiles_x, int64_t tiles_y, int64_t W, int64_t H, int64_t F_rt,
                  const int64_t* offsets, const int32_t* gauss, const T* means2d,
                  const T* conics, const T* opac, const T* feat, const double* fps, T* out_accum,
                  T* out_T, int32_t* out_last, int32_t* out_count, uint16_t* rows_hit,
                  const int32_t* tile_order, int64_t* next_tile) {
  typedef typename Vec<T>::v V;
  typedef typename Vec<T>::m M;
  const int64_t F = FC > 0 ? FC : F_rt;
  // per-row feature slots: FC when it is a constant (the rows' accumulators packed, 4 KB for
  // 16 rows of 4 channels), else MAXF
  constexpr int64_t FS = FC > 0 ? FC : MAXF;
  const int64_t n_tiles = tiles_x * tiles_y;
  V lane;
  for (int l = 0; l < TILE; ++l) lane[l] = T(l);
  for (int64_t c; (c = __atomic_fetch_add(next_tile, 1, __ATOMIC_RELAXED)) < n_tiles;) {
    const Tile tl = tile_at(c, tile_order, tiles_x, W, H);
    const int64_t t = tl.t, x0 = tl.x0, y0 = tl.y0;
    const int rows = tl.rows, cols = tl.cols;
    V Tr[TILE], acc[TILE * FS];
    M last[TILE], count[TILE], done[TILE];
    bool alive[TILE];
    const V pxc = lane + splat<V>(T(x0)) + splat<V>(T(0.5));  // == T(x0 + j) + 0.5 exactly
    const M outside = vge(lane, splat<V>(T(cols)));
    int n_alive = rows;
    for (int i = 0; i < TILE; ++i) {
      Tr[i] = splat<V>(T(1));
      last[i] = count[i] = M{};
      done[i] = outside;
      alive[i] = i < rows;
      for (int64_t f = 0; f < F; ++f) acc[i * FS + f] = V{};
    }
    const int64_t k0 = offsets[t], k1 = offsets[t + 1];
    for (int64_t k = k0; k < k1 && n_alive > 0; ++k) {
      if (k + PAIR_PREFETCH < k1) prefetch_pair(gauss[k + PAIR_PREFETCH], means2d, conics, opac, feat, F, fps);
      Pair<T> p;
      if (!load_pair(gauss[k], means2d, conics, opac, feat, F, fps, p)) { rows_hit[k] = 0; continue; }
      const T mx = p.mx, my = p.my, a = p.a, b = p.b, c = p.c, op = p.op;
      const T* fg = p.fg;
      int i0, i1;
      row_range(p.fp, (double)my, (double)y0, rows, i0, i1);
      const V dx = splat<V>(mx) - pxc;
      const V adx2 = splat<V>(a) * dx * dx;
      const typename Vec<T>::mi lk = (typename Vec<T>::mi)(k - k0 + 1);
      uint32_t hit = 0;  // bit i: the pair blended a pixel of row i
      int i = i0;
      // four (then two) rows per step, each statement for all of them (q = 0 .. NQ - 1): a
      // row's exp is a long dependency chain, and one row at a time left the out-of-order
      // core about one chain to work on; interleaved chains overlap. The same per-lane
      // arithmetic as the one-row loop below (a dead row's lanes are all done, so masked):
      // bit-identical.
      auto rows_step = [&](auto nq, int i) {
        constexpr int NQ = decltype(nq)::value;
        bool none = true;
        for (int q = 0; q < NQ; ++q) none &= !alive[i + q];
        if (none) return;
        T dy[NQ];
        V power[NQ], alpha[NQ], test_T[NQ], w[NQ];
        M pos[NQ], valid[NQ], stop[NQ], contrib[NQ];
        for (int q = 0; q < NQ; ++q) dy[q] = my - (T(y0 + i + q) + T(0.5));
        for (int q = 0; q < NQ; ++q)
          power[q] = splat<V>(T(-0.5)) * (adx2 + splat<V>(c * dy[q] * dy[q])) - splat<V>(b) * dx * splat<V>(dy[q]);
        for (int q = 0; q < NQ; ++q) vle_to(pos[q], power[q], splat<V>(T(0)));
        for (int q = 0; q < NQ; ++q) vsel2_to(alpha[q], pos[q], power[q], splat<V>(T(0)));
        vexpn<NQ>(alpha);
        for (int q = 0; q < NQ; ++q) alpha[q] = splat<V>(op) * alpha[q];
#if SPLAT_NATIVE_BYTES == 64
        for (int q = 0; q < NQ; ++q)
          alpha[q] = alpha[q] < splat<V>(Consts<T>::alpha_max) ? alpha[q] : splat<V>(Consts<T>::alpha_max);
        for (int q = 0; q < NQ; ++q) valid[q] = pos[q] & (alpha[q] >= splat<V>(Consts<T>::alpha_min)) & ~done[i + q];
        for (int q = 0; q < NQ; ++q) test_T[q] = Tr[i + q] * (splat<V>(T(1)) - alpha[q]);
        for (int q = 0; q < NQ; ++q) stop[q] = valid[q] & (test_T[q] < splat<V>(Consts<T>::t_min));
#else  // the same, each compare and select written into its (memory) destination part by part
        M lt_max[NQ];
        for (int q = 0; q < NQ; ++q) vlt_to(lt_max[q], alpha[q], splat<V>(Consts<T>::alpha_max));
        for (int q = 0; q < NQ; ++q) vsel2_to(alpha[q], lt_max[q], alpha[q], splat<V>(Consts<T>::alpha_max));
        for (int q = 0; q < NQ; ++q) vge_to(valid[q], alpha[q], splat<V>(Consts<T>::alpha_min));
        for (int q = 0; q < NQ; ++q) valid[q] = pos[q] & valid[q] & ~done[i + q];
        for (int q = 0; q < NQ; ++q) test_T[q] = Tr[i + q] * (splat<V>(T(1)) - alpha[q]);
        for (int q = 0; q < NQ; ++q) vlt_to(stop[q], test_T[q], splat<V>(Consts<T>::t_min));
        for (int q = 0; q < NQ; ++q) stop[q] = valid[q] & stop[q];
#endif
        for (int q = 0; q < NQ; ++q) contrib[q] = valid[q] & ~stop[q];
        for (int q = 0; q < NQ; ++q) hit |= (uint32_t)any_lane(contrib[q]) << (i + q);
        for (int q = 0; q < NQ; ++q) vsel2_to(w[q], contrib[q], alpha[q] * Tr[i + q], splat<V>(T(0)));
        for (int64_t f = 0; f < F; ++f)
          for (int q = 0; q < NQ; ++q) vfma_to(acc[(i + q) * FS + f], w[q], splat<V>(fg[f]));
        for (int q = 0; q < NQ; ++q) {
          vsel_to(Tr[i + q], contrib[q], test_T[q]);
          vsel_to(last[i + q], contrib[q], splat<M>(lk));
          if constexpr (CNT) count[i + q] -= contrib[q];
        }
#if SPLAT_NATIVE_BYTES == 64
        M any_stop = stop[0];
        for (int q = 1; q < NQ; ++q) any_stop |= stop[q];
        const bool stopped = any_lane(any_stop);
#else
        const bool stopped = any_lane_of(stop, NQ);
#endif
        if (stopped) {
          for (int q = 0; q < NQ; ++q) {
            done[i + q] |= stop[q];
            if (alive[i + q] && all_lanes(done[i + q])) { alive[i + q] = false; --n_alive; }
          }
        }
      };
      for (; i + 3 < i1; i += 4) rows_step(std::integral_constant<int, 4>{}, i);
      for (; i + 1 < i1; i += 2) rows_step(std::integral_constant<int, 2>{}, i);
      for (; i < i1; ++i) {
        if (!alive[i]) continue;
        const T dy = my - (T(y0 + i) + T(0.5));
        const V power = splat<V>(T(-0.5)) * (adx2 + splat<V>(c * dy * dy)) - splat<V>(b) * dx * splat<V>(dy);
        const M pos = vle(power, splat<V>(T(0)));
        V alpha = splat<V>(op) * vexp(vsel(pos, power, splat<V>(T(0))));
        alpha = vsel(vlt(alpha, splat<V>(Consts<T>::alpha_max)), alpha, splat<V>(Consts<T>::alpha_max));
        const M valid = pos & vge(alpha, splat<V>(Consts<T>::alpha_min)) & ~done[i];
        const V test_T = Tr[i] * (splat<V>(T(1)) - alpha);
        const M stop = valid & vlt(test_T, splat<V>(Consts<T>::t_min));
        const M contrib = valid & ~stop;
        hit |= (uint32_t)any_lane(contrib) << i;
        const V w = vsel(contrib, alpha * Tr[i], splat<V>(T(0)));
        for (int64_t f = 0; f < F; ++f) vfma_to(acc[i * FS + f], w, splat<V>(fg[f]));
        vsel_to(Tr[i], contrib, test_T);
        vsel_to(last[i], contrib, splat<M>(lk));
        if constexpr (CNT) count[i] -= contrib;
        if (any_lane(stop)) {
          done[i] |= stop;
          if (all_lanes(done[i])) { alive[i] = false; --n_alive; }
        }
      }
      rows_hit[k] = (uint16_t)hit;
    }
    for (int i = 0; i < rows; ++i)
      store_tile_row<T, FS>(tl, i, W, F, Tr, last, CNT ? count : nullptr, acc, out_accum, out_T, out_last, out_count);
  }
}

#if defined(__AVX512F__)
// forward_impl<float, 4, false> (the rasterizer's case) with its per-lane masks in AVX-512 mask
// registers. Written with GCC's vector extensions, the masks were vectors of 16 ints: each
// comparison result was widened into a zmm register (vmovdqa32 {z}), combined with vector
// and / andnot, and narrowed again for every select (vpcmpneqd / vptestmd), `done` lived in
// memory as a vector, and every `last` update was a load, a masked broadcast and a store;
// the four-row step ran ~82 instructions per row. Here pos / valid / stop / contrib are
// __mmask16 values, `done` a 16-bit mask per row, `last` a masked store, and the arithmetic
// the very vector expressions of forward_impl (the same contractions): bit-identical to it.
inline void forward_f4_avx512(int64_t tiles_x, int64_t tiles_y, int64_t W, int64_t H, const int64_t* offsets,
                              const int32_t* gauss, const float* means2d, const float* conics, const float* opac,
                              const float* feat, const double* fps, float* out_accum, float* out_T,
                              int32_t* out_last, uint16_t* rows_hit, const int32_t* tile_order,
                              int64_t* next_tile) {
  typedef Vec<float>::v V;
  constexpr int64_t F = 4;
  const int64_t n_tiles = tiles_x * tiles_y;
  V lane;
  for (int l = 0; l < TILE; ++l) lane[l] = float(l);
  const __m512 zero = _mm512_setzero_ps(), amin = _mm512_set1_ps(Consts<float>::alpha_min),
               amax = _mm512_set1_ps(Consts<float>::alpha_max), tmin = _mm512_set1_ps(Consts<float>::t_min);
  for (int64_t c; (c = __atomic_fetch_add(next_tile, 1, __ATOMIC_RELAXED)) < n_tiles;) {
    const Tile tl = tile_at(c, tile_order, tiles_x, W, H);
    const int64_t t = tl.t, x0 = tl.x0, y0 = tl.y0;
    const int rows = tl.rows, cols = tl.cols;
    V Tr[TILE], acc[TILE * F];
    Vec<float>::m last[TILE];
    __mmask16 done[TILE];
    bool alive[TILE];
    const V pxc = lane + splat<V>(float(x0)) + splat<V>(0.5f);
    const __mmask16 outside = (__mmask16)(0xFFFFu << cols);  // lanes j >= cols
    int n_alive = rows;
    for (int i = 0; i < TILE; ++i) {
      Tr[i] = splat<V>(1.0f);
      last[i] = Vec<float>::m{};
      done[i] = outside;
      alive[i] = i < rows;
      for (int64_t f = 0; f < F; ++f) acc[i * F + f] = V{};
    }
    const int64_t k0 = offsets[t], k1 = offsets[t + 1];
    for (int64_t k = k0; k < k1 && n_alive > 0; ++k) {
      if (k + PAIR_PREFETCH < k1) prefetch_pair(gauss[k + PAIR_PREFETCH], means2d, conics, opac, feat, F, fps);
      Pair<float> p;
      if (!load_pair(gauss[k], means2d, conics, opac, feat, F, fps, p)) { rows_hit[k] = 0; continue; }
      const float mx = p.mx, my = p.my, a = p.a, b = p.b, c = p.c, op = p.op;
      const float* fg = p.fg;
      int i0, i1;
      row_range(p.fp, (double)my, (double)y0, rows, i0, i1);
      const V dx = splat<V>(mx) - pxc;
      const V adx2 = splat<V>(a) * dx * dx;
      const __m512i lk = _mm512_set1_epi32((int32_t)(k - k0 + 1));
      uint32_t hit = 0;  // bit i: the pair blended a pixel of row i
      auto rows_step = [&](auto nq, int i) {
        constexpr int NQ = decltype(nq)::value;
        bool none = true;
        for (int q = 0; q < NQ; ++q) none &= !alive[i + q];
        if (none) return;
        float dy[NQ];
        V power[NQ], alpha[NQ];
        __mmask16 pos[NQ], stops[NQ], any_stop = 0;
        for (int q = 0; q < NQ; ++q) dy[q] = my - (float(y0 + i + q) + 0.5f);
        for (int q = 0; q < NQ; ++q)
          power[q] = splat<V>(-0.5f) * (adx2 + splat<V>(c * dy[q] * dy[q])) - splat<V>(b) * dx * splat<V>(dy[q]);
        for (int q = 0; q < NQ; ++q) pos[q] = _mm512_cmp_ps_mask(power[q], zero, _CMP_LE_OQ);
        for (int q = 0; q < NQ; ++q) alpha[q] = _mm512_maskz_mov_ps(pos[q], power[q]);
        vexpn<NQ>(alpha);
        for (int q = 0; q < NQ; ++q) alpha[q] = splat<V>(op) * alpha[q];
        for (int q = 0; q < NQ; ++q) alpha[q] = _mm512_min_ps(alpha[q], amax);  // alpha < amax ? alpha : amax
        for (int q = 0; q < NQ; ++q) {
          const __mmask16 valid = _mm512_mask_cmp_ps_mask(pos[q] & (__mmask16)~done[i + q], alpha[q], amin, _CMP_GE_OQ);
          const V test_T = Tr[i + q] * (splat<V>(1.0f) - alpha[q]);
          const __mmask16 stop = _mm512_mask_cmp_ps_mask(valid, test_T, tmin, _CMP_LT_OQ);
          const __mmask16 contrib = valid & (__mmask16)~stop;
          hit |= (uint32_t)(contrib != 0) << (i + q);
          const V w = _mm512_maskz_mul_ps(contrib, alpha[q], Tr[i + q]);
          for (int64_t f = 0; f < F; ++f) acc[(i + q) * F + f] += w * splat<V>(fg[f]);
          Tr[i + q] = _mm512_mask_mov_ps(Tr[i + q], contrib, test_T);
          _mm512_mask_storeu_epi32(&last[i + q], contrib, lk);
          stops[q] = stop;
          any_stop |= stop;
        }
        if (any_stop) {
          for (int q = 0; q < NQ; ++q) {
            done[i + q] |= stops[q];
            if (alive[i + q] && done[i + q] == 0xFFFF) { alive[i + q] = false; --n_alive; }
          }
        }
      };
      int i = i0;
      for (; i + 3 < i1; i += 4) rows_step(std::integral_constant<int, 4>{}, i);
      for (; i + 1 < i1; i += 2) rows_step(std::integral_constant<int, 2>{}, i);
      for (; i < i1; ++i) rows_step(std::integral_constant<int, 1>{}, i);
      rows_hit[k] = (uint16_t)hit;
    }
    for (int i = 0; i < rows; ++i)
      store_tile_row<float, F>(tl, i, W, F, Tr, last, nullptr, acc, out_accum, out_T, out_last, nullptr);
  }
}
#endif

// Per pair k the gradient row v_pair[k * (6 + F) + ...] = (v_mx, v_my, v_a, v_b, v_c,
// v_op, v_feat[0..F)), written for the pairs k0 .. k0 + max_last of each tile (zeros where
// nothing contributed); live[k] = 1 for those, 0 for the rest (never written, never read).
// Only the first Fa feature channels are visited: the caller passes Fa < F when the cotangent
// of channels Fa..F-1 is zero everywhere (their terms are exactly zero: the depth channel of a
// photometric loss), and their gradient rows stay 0.
// FC > 0: Fa == FC as a compile-time constant (the feature loops unrolled, their sums in
// registers; 3 and 4 are the rasterizer's photometric and RGB + depth cases).
template <typename T, int FC>
void backward_impl(int64_t tiles_x, int64_t tiles_y, int64_t W, int64_t H, int64_t F, int64_t Fa_rt,
                   const int64_t* offsets, const int32_t* gauss, const T* means2d,
                   const T* conics, const T* opac, const T* feat, const double* fps, const T* out_T,
                   const int32_t* out_last, const uint16_t* rows_hit, const T* v_accum, const T* v_T,
                   T* v_pair, uint8_t* live, const int32_t* tile_order, int64_t* next_tile) {
  typedef typename Vec<T>::v V;
  typedef typename Vec<T>::m M;
  const int64_t Fa = FC > 0 ? FC : Fa_rt;
  constexpr int64_t FS = FC > 0 ? FC : MAXF;  // per-row feature slots (see forward_impl)
  const int64_t n_tiles = tiles_x * tiles_y;
  const int64_t S = 6 + F;
  V lane;
  for (int l = 0; l < TILE; ++l) lane[l] = T(l);
  for (int64_t c; (c = __atomic_fetch_add(next_tile, 1, __ATOMIC_RELAXED)) < n_tiles;) {
    const Tile tl = tile_at(c, tile_order, tiles_x, W, H);
    const int64_t t = tl.t, x0 = tl.x0, y0 = tl.y0;
    const int rows = tl.rows, cols = tl.cols;
    const int64_t k0 = offsets[t], k1 = offsets[t + 1];
    if (k1 <= k0) continue;
    V Tr[TILE], vTT[TILE], rec[TILE * FS], vacc[TILE * FS];
    M last[TILE];
    int64_t max_last = 0;  // 1 + the tile's last contributing pair (over its pixels)
    const V pxc = lane + splat<V>(T(x0)) + splat<V>(T(0.5));
    for (int i = 0; i < TILE; ++i) {
      Tr[i] = splat<V>(T(1));
      vTT[i] = V{};
      last[i] = M{};
      for (int64_t f = 0; f < Fa; ++f) rec[i * FS + f] = vacc[i * FS + f] = V{};
      if (i >= rows) continue;
      const int64_t row = (y0 + i) * W + x0;
      if (sizeof(T) == 4 && cols == TILE) {  // a full row: vector loads (float: M is int32)
        std::memcpy(&Tr[i], out_T + row, sizeof(V));
        V vt;
        std::memcpy(&vt, v_T + row, sizeof(V));
        vTT[i] = vt * Tr[i];  // dL/dT_final * T_final
        std::memcpy(&last[i], out_last + row, sizeof(M));
        for (int j = 0; j < TILE; ++j) max_last = std::max<int64_t>(max_last, last[i][j]);
#ifdef SPLAT_SHUFFLE
        if (F == 4) {
          Vec<float>::v ch[4];
          deinterleave4(reinterpret_cast<const float*>(v_accum + row * 4), ch);
          for (int64_t f = 0; f < Fa; ++f) std::memcpy(&vacc[i * FS + f], &ch[f], sizeof(V));
          continue;
        }
#endif
        for (int j = 0; j < cols; ++j)
          for (int64_t f = 0; f < Fa; ++f) vacc[i * FS + f][j] = v_accum[(row + j) * F + f];
        continue;
      }
      for (int j = 0; j < cols; ++j) {
        const T tf = out_T[row + j];
        Tr[i][j] = tf;
        vTT[i][j] = v_T[row + j] * tf;  // dL/dT_final * T_final
        last[i][j] = out_last[row + j];
        max_last = std::max<int64_t>(max_last, out_last[row + j]);
        for (int64_t f = 0; f < Fa; ++f) vacc[i * FS + f][j] = v_accum[(row + j) * F + f];
      }
    }
    // Rows are written once each (zeros where the pair blends nothing): a zeroing loop over the
    // runtime S compiled to a memset call per pair, ~4% of a 512x512 forward+backward; with
    // S = 10 (F = 4, the rasterizer's case) a fixed-size clear is a few inline stores.
    auto clear = [S](T* p, int64_t from) {
      if (S == 10 && from == 0) {
        std::memset(p, 0, 10 * sizeof(T));
      } else {
        for (int64_t q = from; q < S; ++q) p[q] = T(0);
      }
    };
    // pairs k0 + max_last .. k1 (behind every pixel's last contributor: in a saturated tile
    // most of its list) blend nothing; their rows are not written (clearing them was ~6-8 ms
    // of random writes at 100k 512x512) and live[k] = 0 tells the reduction to skip them
    std::memset(live + k0, 1, (size_t)max_last);
    std::memset(live + k0 + max_last, 0, (size_t)(k1 - k0 - max_last));
    for (int64_t k = k0 + max_last - 1; k >= k0; --k) {
      if (k - PAIR_PREFETCH >= k0) prefetch_pair(gauss[k - PAIR_PREFETCH], means2d, conics, opac, feat, F, fps);
      // row k: the tile's rows are written in sequence (by the Gaussian's slot instead, they
      // were ~430k scattered 40-byte writes, ~6 ms of a ~75 ms backward on the fern cell)
      T* gp = v_pair + k * S;
      const int32_t local = (int32_t)(k - k0);
      // the rows where the forward blended a pixel of this pair (rows_hit): in every other row
      // no lane passes the mask m below, so skipping them changes no bit (a fully masked row
      // adds +0 to sums that are never -0 and changes no state)
      uint32_t hit = rows_hit[k];
      Pair<T> p;
      if (!hit || !load_pair(gauss[k], means2d, conics, opac, feat, F, fps, p)) { clear(gp, 0); continue; }
      const T mx = p.mx, my = p.my, a = p.a, b = p.b, c = p.c, op = p.op;
      const T* fg = p.fg;
      // per lane: G0 = sum over rows of dL/dG (masked), G1 = sum dy dL/dG, G2 = sum dy^2 dL/dG;
      // dx is constant along a lane, so the five conic/mean gradients follow from these three
      // once per pair (v_power = op dL/dG, power = -(a dx^2 + c dy^2) / 2 - b dx dy)
      V G0{}, G1{}, G2{}, g_f[MAXF];
      for (int64_t f = 0; f < Fa; ++f) g_f[f] = V{};
      const V dx = splat<V>(mx) - pxc;
      const V adx2 = splat<V>(a) * dx * dx;
      const M lk = splat<M>((typename Vec<T>::mi)local);
      bool any = false;
      // the hit rows NQ per step (as in forward_impl: interleaved exp chains), in ascending
      // order, so the sums take the rows in the order of a one-row loop
      auto rows_step = [&](auto nq) {
        constexpr int NQ = decltype(nq)::value;
        int ri[NQ];
        for (int q = 0; q < NQ; ++q) { ri[q] = __builtin_ctz(hit); hit &= hit - 1; }
        T dy[NQ];
        for (int q = 0; q < NQ; ++q) dy[q] = my - (T(y0 + ri[q]) + T(0.5));
        V power[NQ], G[NQ], raw[NQ], alpha[NQ], inv_one_m[NQ], Tfront[NQ], am[NQ], wm[NQ], v_alpha[NQ], vG[NQ];
        M pos[NQ], m[NQ], m2[NQ];
        for (int q = 0; q < NQ; ++q)
          power[q] = splat<V>(T(-0.5)) * (adx2 + splat<V>(c * dy[q] * dy[q])) - splat<V>(b) * dx * splat<V>(dy[q]);
        for (int q = 0; q < NQ; ++q) vle_to(pos[q], power[q], splat<V>(T(0)));
        for (int q = 0; q < NQ; ++q) vsel2_to(G[q], pos[q], power[q], splat<V>(T(0)));
        vexpn<NQ>(G);
        for (int q = 0; q < NQ; ++q) raw[q] = splat<V>(op) * G[q];
#if SPLAT_NATIVE_BYTES == 64
        for (int q = 0; q < NQ; ++q)
          alpha[q] = raw[q] < splat<V>(Consts<T>::alpha_max) ? raw[q] : splat<V>(Consts<T>::alpha_max);
        for (int q = 0; q < NQ; ++q)
          m[q] = pos[q] & (lk < last[ri[q]]) & (alpha[q] >= splat<V>(Consts<T>::alpha_min));
        M any_m = m[0];
        for (int q = 1; q < NQ; ++q) any_m |= m[q];
        any |= any_lane(any_m);
#else  // the same, each compare and select written into its destination part by part (forward_impl)
        M tmp[NQ];
        for (int q = 0; q < NQ; ++q) vlt_to(tmp[q], raw[q], splat<V>(Consts<T>::alpha_max));
        for (int q = 0; q < NQ; ++q) vsel2_to(alpha[q], tmp[q], raw[q], splat<V>(Consts<T>::alpha_max));
        for (int q = 0; q < NQ; ++q) {
          vlt_to(m[q], lk, last[ri[q]]);
          vge_to(tmp[q], alpha[q], splat<V>(Consts<T>::alpha_min));
          m[q] = pos[q] & m[q] & tmp[q];
        }
        any |= any_lane_of(m, NQ);
#endif
        for (int q = 0; q < NQ; ++q) inv_one_m[q] = recip(splat<V>(T(1)) - alpha[q]);
        for (int q = 0; q < NQ; ++q) Tfront[q] = Tr[ri[q]] * inv_one_m[q];
        for (int q = 0; q < NQ; ++q) vsel2_to(am[q], m[q], alpha[q], V{});  // other lanes: rec, g_f unchanged
        for (int q = 0; q < NQ; ++q) wm[q] = am[q] * Tfront[q];
        for (int q = 0; q < NQ; ++q) v_alpha[q] = V{};
        for (int64_t f = 0; f < Fa; ++f) {
          for (int q = 0; q < NQ; ++q) {
            V& rp = rec[ri[q] * FS + f];
            const V vp = vacc[ri[q] * FS + f];
            const V d = splat<V>(fg[f]) - rp;
            vfma_to(g_f[f], wm[q], vp);
            vfma_to(v_alpha[q], d, vp);
            vfma_to(rp, am[q], d);  // alpha f + (1 - alpha) rp
          }
        }
        for (int q = 0; q < NQ; ++q) v_alpha[q] = v_alpha[q] * Tfront[q] - vTT[ri[q]] * inv_one_m[q];
        for (int q = 0; q < NQ; ++q) vsel_to(Tr[ri[q]], m[q], Tfront[q]);
#if SPLAT_NATIVE_BYTES == 64
        for (int q = 0; q < NQ; ++q) m2[q] = m[q] & (raw[q] <= splat<V>(Consts<T>::alpha_max));
#else
        for (int q = 0; q < NQ; ++q) vle_to(m2[q], raw[q], splat<V>(Consts<T>::alpha_max));
        for (int q = 0; q < NQ; ++q) m2[q] = m[q] & m2[q];
#endif
        for (int q = 0; q < NQ; ++q) vsel2_to(vG[q], m2[q], G[q] * v_alpha[q], V{});
        for (int q = 0; q < NQ; ++q) {
          G0 += vG[q];
          vfma_to(G1, vG[q], splat<V>(dy[q]));
          vfma_to(G2, vG[q], splat<V>(dy[q] * dy[q]));
        }
      };
      // four rows per step, then two, then one (fern checkpoint, one thread, backward +
      // reduction: four 53.7 / 50.2 / 51.8 / 52.5 ms against two 53.5 / 59.2 / 56.4 / 51.6)
      for (int n = __builtin_popcount(hit); n >= 4; n -= 4) rows_step(std::integral_constant<int, 4>{});
      if (__builtin_popcount(hit) >= 2) rows_step(std::integral_constant<int, 2>{});
      if (hit) rows_step(std::integral_constant<int, 1>{});
      if (!any) { clear(gp, 0); continue; }
      const V S0 = splat<V>(op) * G0, S1 = splat<V>(op) * G1;
#if defined(__AVX512F__)
      if constexpr (sizeof(T) == 4) {
        if (Fa >= 2) {  // eight of the sums at once (hsum8), bit-identical
          V r[8] = {-(splat<V>(a) * dx * S0 + splat<V>(b) * S1), -(splat<V>(c) * S1 + splat<V>(b) * dx * S0),
                    splat<V>(T(-0.5)) * dx * dx * S0, -(dx * S1), G2, G0, g_f[0], g_f[1]};
          float h[8];
          hsum8(r, h);
          for (int j = 0; j < 8; ++j) gp[j] = h[j];
          gp[4] = T(-0.5) * op * gp[4];
          for (int64_t f = 2; f < Fa; ++f) gp[6 + f] = hsum<T>(g_f[f]);
          clear(gp, 6 + Fa);
          continue;
        }
      }
#endif
      gp[0] = hsum<T>(-(splat<V>(a) * dx * S0 + splat<V>(b) * S1));
      gp[1] = hsum<T>(-(splat<V>(c) * S1 + splat<V>(b) * dx * S0));
      gp[2] = hsum<T>(splat<V>(T(-0.5)) * dx * dx * S0);
      gp[3] = hsum<T>(-(dx * S1));
      gp[4] = T(-0.5) * op * hsum<T>(G2);
      gp[5] = hsum<T>(G0);
      for (int64_t f = 0; f < Fa; ++f) gp[6 + f] = hsum<T>(g_f[f]);
      clear(gp, 6 + Fa);
    }
  }
}

// v_out[g] = sum of the pair gradient rows of Gaussian g (rank r = its position in the depth
// order; its slots ps[r] .. ps[r+1] name its pairs: row slot_pair[j] for slot j, read in slot
// order, the next rows prefetched).
// order; its slots are ps[r] .. ps[r+1], contiguous). Chunks of ranks from a shared counter;
// each Gaussian is summed by one thread in a fixed order, so the result is deterministic.
template <typename T, int SC>
inline void reduce_rows(int64_t S, const T* v_pair, int64_t rows, const int32_t* sp, const uint8_t* live, T* out) {
  // SC > 0: the row length S as a compile-time constant, so the sums stay in registers (the
  // generic loop below keeps them in memory: out may alias v_pair as far as the compiler
  // knows, so it reloads and stores every partial sum, ~3x slower at 1.1 M pairs).
  constexpr int L = SC > 0 ? SC : 6 + MAXF;
  T acc[L];
  const int64_t n = SC > 0 ? SC : S;
  for (int64_t s = 0; s < n; ++s) acc[s] = T(0);
  for (int64_t j = 0; j < rows; ++j) {
    const int64_t k = sp[j];
    if (!live[k]) continue;  // a pair the backward did not reach (row unwritten)
    const T* src = v_pair + k * n;
    for (int64_t s = 0; s < n; ++s) acc[s] += src[s];
  }
  for (int64_t s = 0; s < n; ++s) out[s] = acc[s];
}

constexpr int64_t RED_PREFETCH = 16;  // slots ahead

// With visible (n Gaussians, the ones in `order` marked 1), the rows of the others are set to
// zero here, in work items after the ranks' (v_out then needs no clearing beforehand: a
// separate torch.zeros of the [N, 6 + F] gradient cost ~1 ms of cold-cache writes per training
// iteration at 200k Gaussians).
template <typename T>
void reduce_impl(int64_t m, const int64_t* order, const int64_t* ps, int64_t S, const T* v_pair,
                 const int32_t* slot_pair, const uint8_t* live, int64_t n, const uint8_t* visible, T* v_out,
                 int64_t* next_chunk) {
  constexpr int64_t CHUNK = 2048;
  const int64_t rank_items = (m + CHUNK - 1) / CHUNK;
  const int64_t items = rank_items + (visible ? (n + CHUNK - 1) / CHUNK : 0);
  for (int64_t ch; (ch = __atomic_fetch_add(next_chunk, 1, __ATOMIC_RELAXED)) < items;) {
    if (ch >= rank_items) {  // zero rows of the Gaussians in no tile list
      const int64_t g0 = (ch - rank_items) * CHUNK, g1 = std::min(n, g0 + CHUNK);
      for (int64_t g = g0; g < g1; ++g)
        if (!visible[g])
          for (int64_t s = 0; s < S; ++s) v_out[g * S + s] = T(0);
      continue;
    }
    const int64_t r1 = std::min(m, (ch + 1) * CHUNK);
    const int64_t pend = ps[r1];
    for (int64_t r = ch * CHUNK; r < r1; ++r) {
      T* out = v_out + order[r] * S;
      const int64_t rows = ps[r + 1] - ps[r];
      const int32_t* sp = slot_pair + ps[r];
      // the rows of the next Gaussians (random addresses: pairs are numbered tile by tile)
      for (int64_t j = ps[r] + RED_PREFETCH; j < std::min(ps[r + 1] + RED_PREFETCH, pend); ++j) {
        __builtin_prefetch(v_pair + (int64_t)slot_pair[j] * S);
        __builtin_prefetch(v_pair + (int64_t)slot_pair[j] * S + S - 1);
      }
      if (S == 10) {  // F = 4: RGB + depth, the rasterizer's case
        reduce_rows<T, 10>(S, v_pair, rows, sp, live, out);
      } else if (S <= 6 + MAXF) {
        reduce_rows<T, 0>(S, v_pair, rows, sp, live, out);
      } else {
        for (int64_t s = 0; s < S; ++s) out[s] = T(0);
        for (int64_t j = 0; j < rows; ++j)
          if (live[sp[j]])
            for (int64_t s = 0; s < S; ++s) out[s] += v_pair[(int64_t)sp[j] * S + s];
      }
    }
  }
}

// forward_impl specialised for F == 4 (RGB + depth, the rasterizer's case) and for whether the
// per-pixel counts are wanted (cnt non-null).
template <typename T>
void forward_for(int64_t tx, int64_t ty, int64_t W, int64_t H, int64_t F, const int64_t* off,
                 const int32_t* gs, const T* m, const T* co, const T* op, const T* fe, const double* fp,
                 T* acc, T* Tf, int32_t* last, int32_t* cnt, uint16_t* hit, const int32_t* ord, int64_t* nth) {
#if defined(__AVX512F__)
  if (std::is_same<T, float>::value && F == 4 && !cnt) {
    forward_f4_avx512(tx, ty, W, H, off, gs, (const float*)m, (const float*)co, (const float*)op, (const float*)fe,
                      fp, (float*)acc, (float*)Tf, last, hit, ord, nth);
    return;
  }
#endif
  if (F == 4 && !cnt) {
    forward_impl<T, 4, false>(tx, ty, W, H, F, off, gs, m, co, op, fe, fp, acc, Tf, last, cnt, hit, ord, nth);
  } else if (F == 4) {
    forward_impl<T, 4, true>(tx, ty, W, H, F, off, gs, m, co, op, fe, fp, acc, Tf, last, cnt, hit, ord, nth);
  } else if (!cnt) {
    forward_impl<T, 0, false>(tx, ty, W, H, F, off, gs, m, co, op, fe, fp, acc, Tf, last, cnt, hit, ord, nth);
  } else {
    forward_impl<T, 0, true>(tx, ty, W, H, F, off, gs, m, co, op, fe, fp, acc, Tf, last, cnt, hit, ord, nth);
  }
}

// backward_impl specialised for the usual active channel counts (RGB: 3, RGB + depth: 4).
template <typename T>
void backward_for_active(int64_t tx, int64_t ty, int64_t W, int64_t H, int64_t F, int64_t Fa,
                         const int64_t* off, const int32_t* gs, const T* m, const T* co, const T* op,
                         const T* fe, const double* fp, const T* Tf, const int32_t* last, const uint16_t* hit,
                         const T* vacc, const T* vT, T* vpair, uint8_t* live, const int32_t* ord, int64_t* nth) {
  if (Fa == 3) {
    backward_impl<T, 3>(tx, ty, W, H, F, Fa, off, gs, m, co, op, fe, fp, Tf, last, hit, vacc, vT, vpair, live, ord, nth);
  } else if (Fa == 4) {
    backward_impl<T, 4>(tx, ty, W, H, F, Fa, off, gs, m, co, op, fe, fp, Tf, last, hit, vacc, vT, vpair, live, ord, nth);
  } else {
    backward_impl<T, 0>(tx, ty, W, H, F, Fa, off, gs, m, co, op, fe, fp, Tf, last, hit, vacc, vT, vpair, live, ord, nth);
  }
}

// See splat2_active_f32 below.
template <typename T>
int64_t active_channels(int64_t n, int64_t F, const T* v) {
  int64_t act = 0;
  for (int64_t i = 0; i < n && act < F; ++i)
    for (int64_t f = F - 1; f >= act; --f)
      if (v[i * F + f] != T(0)) { act = f + 1; break; }
  return act;
}

}  // namespace

extern "C" {

int splat2_abi_version() { return 18; }

// 1 + the last feature channel f < F with a nonzero value (x != 0: NaN counts, -0.0 does not)
// among the n pixels of v [n, F] (contiguous), 0 if none: the backward skips the trailing
// channels whose cotangent is zero everywhere. One pass over v (a strided torch .any() per
// channel cost ~4 ms each at 185k pixels).
int64_t splat2_active_f32(int64_t n, int64_t F, const float* v) { return active_channels(n, F, v); }
int64_t splat2_active_f64(int64_t n, int64_t F, const double* v) { return active_channels(n, F, v); }

// Widest vector instruction set this build was compiled for: 512, 256 or 128 (bits).
int splat2_simd_bits() {
#if defined(__AVX512F__)
  return 512;
#elif defined(__AVX2__)
  return 256;
#else
  return 128;
#endif
}

// Stable ascending order of the visible Gaussians by depth (ties by index): LSD radix sort,
// 4 passes of 8 bits over the float32 bit pattern made order-preserving (sign flip), a pass
// skipped when all keys share its byte. Writes the M visible indices to order [N] and returns
// M; buf [N] int64 and keys [2 N] uint32 are scratch.
int64_t splat2_depth_order_f32(int64_t n, const float* depths, const uint8_t* visible,
                               int64_t* order, int64_t* buf, uint32_t* keys) {
  int64_t m = 0;
  for (int64_t i = 0; i < n; ++i) {
    if (!visible[i]) continue;
    uint32_t u;
    std::memcpy(&u, depths + i, 4);
    if (u == 0x80000000u) u = 0;  // -0.0 ties with +0.0, as in a comparison sort
    keys[m] = (u & 0x80000000u) ? ~u : (u | 0x80000000u);
    order[m++] = i;
  }
  int64_t* src = order;
  int64_t* dst = buf;
  uint32_t* ksrc = keys;
  uint32_t* kdst = keys + n;
  for (int shift = 0; shift < 32 && m > 0; shift += 8) {
    int64_t cnt[257] = {0};
    for (int64_t i = 0; i < m; ++i) ++cnt[((ksrc[i] >> shift) & 255u) + 1];
    if (cnt[((ksrc[0] >> shift) & 255u) + 1] == m) continue;
    for (int b = 0; b < 256; ++b) cnt[b + 1] += cnt[b];
    for (int64_t i = 0; i < m; ++i) {
      const int64_t p = cnt[(ksrc[i] >> shift) & 255u]++;
      dst[p] = src[i];
      kdst[p] = ksrc[i];
    }
    std::swap(src, dst);
    std::swap(ksrc, kdst);
  }
  if (src != order) std::memcpy(order, src, sizeof(int64_t) * m);
  return m;
}

// Tile lists by a parallel counting sort, in two passes over NCH fixed chunks of the depth
// order (chunk c = ranks [c M / NCH, (c + 1) M / NCH)), each pass a work item per chunk from a
// shared counter: splat2_bin_count writes counts [NCH, n_tiles] (the chunk's pairs per tile) and
// the pair count of every rank into area [M]; the caller turns these into offsets
// [n_tiles + 1], the chunk's first position per tile, base [NCH, n_tiles], and ps [M + 1]
// (prefix sums of the areas); splat2_bin_scatter then writes gauss [P] (each tile's list in
// front-to-back order, as one sequential counting sort would) and slot_pair [P]: Gaussian rank
// r owns slots ps[r] .. ps[r+1] (its tiles row-major), slot j names its pair slot_pair[j], so
// splat2_reduce finds each Gaussian's pair gradients. The output does not depend
// on the number of threads. A Gaussian's tiles: its rectangle rect [N, 4], and with fp
// (footprints [FP N] and binning records [SPREC N] computed with the rectangles, may be null) only
// the tiles its alpha >= 1/255 ellipse can reach (for_tiles).
void splat2_bin_count(int64_t m, const int64_t* order, const int64_t* rect, const double* fps,
                      const int16_t* sps, int64_t tiles_x, int64_t n_tiles, int64_t nch, int64_t* counts, int64_t* area, int64_t* next) {
  for (int64_t c; (c = __atomic_fetch_add(next, 1, __ATOMIC_RELAXED)) < nch;) {
    // per tile row a difference array (+1 at c0, -1 at c1, one spare column): two updates per
    // tile row of a Gaussian instead of one per tile, then a prefix sum along each row
    const int64_t tiles_y = n_tiles / tiles_x, stride = tiles_x + 1;
    int64_t* diff = new int64_t[tiles_y * stride]();
    const int64_t k1 = (c + 1) * m / nch;
    for (int64_t k = c * m / nch; k < k1; ++k) {
      const int64_t g = order[k];
      if (k + PREFETCH < k1) prefetch_gaussian(rect, fps, sps, order[k + PREFETCH]);
      int64_t a = 0;
      for_rows(rect + 4 * g, fps ? fps + FP * g : nullptr, fps ? sps + SPREC * g : nullptr,
               [&](int64_t y, int64_t c0, int64_t c1) {
                 if (c1 <= c0) return;
                 ++diff[y * stride + c0];
                 --diff[y * stride + c1];
                 a += c1 - c0;
               });
      area[k] = a;
    }
    int64_t* cnt = counts + c * n_tiles;
    for (int64_t y = 0; y < tiles_y; ++y) {
      int64_t run = 0;
      for (int64_t x = 0; x < tiles_x; ++x) cnt[y * tiles_x + x] = (run += diff[y * stride + x]);
    }
    delete[] diff;
  }
}

void splat2_bin_scatter(int64_t m, const int64_t* order, const int64_t* rect, const double* fps,
                        const int16_t* sps, int64_t tiles_x, int64_t n_tiles, int64_t nch, const int64_t* base, const int64_t* ps,
                        int32_t* gauss, int32_t* slot_pair, int64_t* next) {
  for (int64_t c; (c = __atomic_fetch_add(next, 1, __ATOMIC_RELAXED)) < nch;) {
    int64_t* cursor = new int64_t[n_tiles];
    for (int64_t t = 0; t < n_tiles; ++t) cursor[t] = base[c * n_tiles + t];
    const int64_t k1 = (c + 1) * m / nch;
    for (int64_t k = c * m / nch; k < k1; ++k) {
      const int64_t g = order[k];
      if (k + PREFETCH < k1) prefetch_gaussian(rect, fps, sps, order[k + PREFETCH]);
      int64_t q = ps[k];
      for_tiles(rect + 4 * g, fps ? fps + FP * g : nullptr, fps ? sps + SPREC * g : nullptr, [&](int64_t y, int64_t x) {
        const int64_t pos = cursor[y * tiles_x + x]++;
        gauss[pos] = (int32_t)g;
        slot_pair[q++] = (int32_t)pos;  // sequential writes
      });
    }
    delete[] cursor;
  }
}

// fp [FP N] float64: per-Gaussian footprint (see footprint()); with rect [4 N] and sp
// [SPREC N] int16 (both may be null) also its binning record (tiles and spans, for_tiles). Chunks of 4096 Gaussians.
void splat2_footprint_f32(int64_t n, const float* co, const float* op, const float* mu, const int64_t* rect,
                          double* fp, int16_t* sp, int64_t* nth) {
  for (int64_t ch; (ch = __atomic_fetch_add(nth, 1, __ATOMIC_RELAXED)) * 4096 < n;)
    for (int64_t g = ch * 4096; g < std::min(n, (ch + 1) * 4096); g += fpv::LN)
      fpv::footprint_block<float>(g, (int)std::min<int64_t>(fpv::LN, n - g), co, op, mu, rect, fp, sp);
}
void splat2_footprint_f64(int64_t n, const double* co, const double* op, const double* mu, const int64_t* rect,
                          double* fp, int16_t* sp, int64_t* nth) {
  for (int64_t ch; (ch = __atomic_fetch_add(nth, 1, __ATOMIC_RELAXED)) * 4096 < n;)
    for (int64_t g = ch * 4096; g < std::min(n, (ch + 1) * 4096); g += fpv::LN)
      fpv::footprint_block<double>(g, (int)std::min<int64_t>(fpv::LN, n - g), co, op, mu, rect, fp, sp);
}
// The scalar footprint() per Gaussian: the reference the vector pass above must match exactly
// (tests/test_raster_tile_culling.py compares them), not used by the rasterizer.
void splat2_footprint_scalar_f32(int64_t n, const float* co, const float* op, const float* mu, const int64_t* rect,
                                 double* fp, int16_t* sp) {
  for (int64_t g = 0; g < n; ++g)
    footprint<float>(co[3 * g], co[3 * g + 1], co[3 * g + 2], op[g], mu[2 * g], mu[2 * g + 1],
                     rect ? rect + 4 * g : nullptr, fp + FP * g, sp ? sp + SPREC * g : nullptr);
}
void splat2_footprint_scalar_f64(int64_t n, const double* co, const double* op, const double* mu, const int64_t* rect,
                                 double* fp, int16_t* sp) {
  for (int64_t g = 0; g < n; ++g)
    footprint<double>(co[3 * g], co[3 * g + 1], co[3 * g + 2], op[g], mu[2 * g], mu[2 * g + 1],
                      rect ? rect + 4 * g : nullptr, fp + FP * g, sp ? sp + SPREC * g : nullptr);
}
void splat2_forward_f32(int64_t tx, int64_t ty, int64_t W, int64_t H, int64_t F,
                        const int64_t* off, const int32_t* gs, const float* m, const float* co,
                        const float* op, const float* fe, const double* fp, float* acc, float* Tf,
                        int32_t* last, int32_t* cnt, uint16_t* hit, const int32_t* ord, int64_t* nth) {
  forward_for<float>(tx, ty, W, H, F, off, gs, m, co, op, fe, fp, acc, Tf, last, cnt, hit, ord, nth);
}
void splat2_forward_f64(int64_t tx, int64_t ty, int64_t W, int64_t H, int64_t F,
                        const int64_t* off, const int32_t* gs, const double* m, const double* co,
                        const double* op, const double* fe, const double* fp, double* acc, double* Tf,
                        int32_t* last, int32_t* cnt, uint16_t* hit, const int32_t* ord, int64_t* nth) {
  forward_for<double>(tx, ty, W, H, F, off, gs, m, co, op, fe, fp, acc, Tf, last, cnt, hit, ord, nth);
}
void splat2_backward_f32(int64_t tx, int64_t ty, int64_t W, int64_t H, int64_t F, int64_t Fa,
                         const int64_t* off, const int32_t* gs, const float* m, const float* co,
                         const float* op, const float* fe, const double* fp, const float* Tf,
                         const int32_t* last, const uint16_t* hit, const float* vacc, const float* vT,
                         float* vpair, uint8_t* live, const int32_t* ord, int64_t* nth) {
  backward_for_active<float>(tx, ty, W, H, F, Fa, off, gs, m, co, op, fe, fp, Tf, last, hit, vacc, vT, vpair, live, ord, nth);
}
void splat2_backward_f64(int64_t tx, int64_t ty, int64_t W, int64_t H, int64_t F, int64_t Fa,
                         const int64_t* off, const int32_t* gs, const double* m,
                         const double* co, const double* op, const double* fe, const double* fp,
                         const double* Tf, const int32_t* last, const uint16_t* hit, const double* vacc,
                         const double* vT, double* vpair, uint8_t* live, const int32_t* ord, int64_t* nth) {
  backward_for_active<double>(tx, ty, W, H, F, Fa, off, gs, m, co, op, fe, fp, Tf, last, hit, vacc, vT, vpair, live, ord, nth);
}
void splat2_reduce_f32(int64_t m, const int64_t* order, const int64_t* ps, int64_t S, const float* v_pair,
                       const int32_t* sp, const uint8_t* live, int64_t n, const uint8_t* visible, float* v_out,
                       int64_t* nth) {
  reduce_impl<float>(m, order, ps, S, v_pair, sp, live, n, visible, v_out, nth);
}
void splat2_reduce_f64(int64_t m, const int64_t* order, const int64_t* ps, int64_t S, const double* v_pair,
                       const int32_t* sp, const uint8_t* live, int64_t n, const uint8_t* visible, double* v_out,
                       int64_t* nth) {
  reduce_impl<double>(m, order, ps, S, v_pair, sp, live, n, visible, v_out, nth);
}

}  // extern "C"
