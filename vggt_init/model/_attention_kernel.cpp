// Fused (flash-style) bf16 softmax attention for CPUs with AVX512-BF16 (vdpbf16ps).
//
// Plain C ABI, no torch headers, no OpenMP: built and loaded by _attention_kernel.py, which runs
// vggt_attn_bf16 on several Python threads sharing one task counter (ctypes drops the GIL).
//
// Layouts (bf16 stored as uint16_t; BH = B * nh; Np = N rounded up to a multiple of KB = 64):
//   q   [BH, N, D]                      contiguous ([B, nh, N, D])
//   kp  [BH, Np/16, D/2, 16, 2]         kp[bh, nb, p, i, e] = k[bh, 16 nb + i, 2 p + e]  (0 past N)
//   vp  [BH, Np/2, D/16, 16, 2]         vp[bh, j, c, i, e]  = v[bh, 2 j + e, 16 c + i]  (0 past N)
//   out [B, N, nh, D]                   token-major, bf16
// so one 64-byte load of kp is the (d, d+1) pairs of 16 keys and one of vp the (key, key+1)
// pairs of 16 output channels: the operand layout of _mm512_dpbf16_ps, whose other operand is a
// broadcast pair of q (for scores) or of P (for P V).
//
// Task = (b, h, block of MQ query rows). Per key block of KB keys and per tile of MR rows:
// scores in float32 (vdpbf16ps), scale 1/sqrt(D) applied to the float32 scores, online softmax
// (running row max m and per-lane partial row sums l, float32), P rounded to bf16, P V accumulated
// in float32 into the row block's output accumulator (rescaled by exp(m_old - m_new)), and at the
// end division by the row sum and rounding to bf16. Each task's arithmetic does not depend on
// which thread runs it, so results are bitwise independent of the thread count.
#include <immintrin.h>

#include <cstdint>
#include <cstring>
#include <limits>

namespace {

constexpr int MR = 6;   // query rows per register tile
constexpr int KB = 64;  // keys per block (4 vectors of 16 scores)
constexpr int MQ = 48;  // query rows per task

inline __m512bh load_bh(const uint16_t* p) { return (__m512bh)_mm512_loadu_si512(p); }

inline __m512bh bcast_pair(const uint16_t* p) {
  int32_t w;
  std::memcpy(&w, p, 4);
  return (__m512bh)_mm512_set1_epi32(w);
}

// exp(x) for float32 lanes: Cephes-style range reduction x = n ln2 + r, |r| <= ln2/2, degree-7
// polynomial, 2^n applied with vscalefps (exact, gives 0 / subnormals for very negative x).
// About 1 ulp. NaN and -inf inputs are clamped to -110 (result 0); +inf to 88.5.
inline __m512 exp_ps(__m512 x) {
  x = _mm512_max_ps(x, _mm512_set1_ps(-110.0f));  // vmaxps returns the 2nd operand for NaN
  x = _mm512_min_ps(x, _mm512_set1_ps(88.5f));
  const __m512 n = _mm512_roundscale_ps(_mm512_mul_ps(x, _mm512_set1_ps(1.44269504088896341f)),
                                        _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  __m512 r = _mm512_fnmadd_ps(n, _mm512_set1_ps(0.693359375f), x);
  r = _mm512_fnmadd_ps(n, _mm512_set1_ps(-2.12194440e-4f), r);
  __m512 y = _mm512_set1_ps(1.9875691500e-4f);
  y = _mm512_fmadd_ps(y, r, _mm512_set1_ps(1.3981999507e-3f));
  y = _mm512_fmadd_ps(y, r, _mm512_set1_ps(8.3334519073e-3f));
  y = _mm512_fmadd_ps(y, r, _mm512_set1_ps(4.1665795894e-2f));
  y = _mm512_fmadd_ps(y, r, _mm512_set1_ps(1.6666665459e-1f));
  y = _mm512_fmadd_ps(y, r, _mm512_set1_ps(5.0000001201e-1f));
  const __m512 r2 = _mm512_mul_ps(r, r);
  y = _mm512_fmadd_ps(y, r2, r);
  y = _mm512_add_ps(y, _mm512_set1_ps(1.0f));
  return _mm512_scalef_ps(y, n);
}

// P V for R rows and DV (<= 4) vectors of 16 output channels starting at channel 16 c0:
// o[r, 16 c0 : 16 (c0 + DV)] = alpha[r] * o[...] + sum_j P[r, 2j:2j+2] . V[2j:2j+2, ...].
template <int D, int R, int DV>
inline void pv_chunk(const uint16_t* vblk, const uint16_t* pbuf, int npairs, const float* alpha,
                     float* o, int c0) {
  __m512 acc[R][DV];
  for (int r = 0; r < R; ++r) {
    const __m512 a = _mm512_set1_ps(alpha[r]);
    for (int c = 0; c < DV; ++c) acc[r][c] = _mm512_mul_ps(_mm512_loadu_ps(o + r * D + 16 * (c0 + c)), a);
  }
  for (int j = 0; j < npairs; ++j) {
    __m512bh vv[DV];
    for (int c = 0; c < DV; ++c) vv[c] = load_bh(vblk + (j * (D / 16) + c0 + c) * 32);
    for (int r = 0; r < R; ++r) {
      const __m512bh pb = bcast_pair(pbuf + r * KB + 2 * j);
      for (int c = 0; c < DV; ++c) acc[r][c] = _mm512_dpbf16_ps(acc[r][c], pb, vv[c]);
    }
  }
  for (int r = 0; r < R; ++r)
    for (int c = 0; c < DV; ++c) _mm512_storeu_ps(o + r * D + 16 * (c0 + c), acc[r][c]);
}

// One tile of R query rows against one key block of nk (1..KB) keys.
//   q: R rows of D (stride D); kblk, vblk: the block's packed keys / values (layouts above);
//   m[R] running max of the scaled scores, l[R] per-lane partial sums, o[R x D] accumulators.
template <int D, int R>
inline void tile(const uint16_t* q, const uint16_t* kblk, const uint16_t* vblk, int nk, float scale,
                 float* m, __m512* l, float* o) {
  alignas(64) uint16_t pbuf[R * KB];
  float alpha[R];
  {
    __m512 s[R][4];
    for (int r = 0; r < R; ++r)
      for (int c = 0; c < 4; ++c) s[r][c] = _mm512_setzero_ps();
    for (int p = 0; p < D / 2; ++p) {
      __m512bh kv[4];
      for (int c = 0; c < 4; ++c) kv[c] = load_bh(kblk + (c * (D / 2) + p) * 32);
      for (int r = 0; r < R; ++r) {
        const __m512bh qb = bcast_pair(q + r * D + 2 * p);
        for (int c = 0; c < 4; ++c) s[r][c] = _mm512_dpbf16_ps(s[r][c], qb, kv[c]);
      }
    }
    if (nk < KB) {  // keys past the end (zero padding) get score -inf, hence P = 0
      const __m512 ninf = _mm512_set1_ps(-std::numeric_limits<float>::infinity());
      for (int c = 0; c < 4; ++c) {
        const int valid = nk - 16 * c;
        const __mmask16 keep = valid >= 16 ? (__mmask16)0xFFFF
                               : valid <= 0 ? (__mmask16)0 : (__mmask16)((1u << valid) - 1u);
        for (int r = 0; r < R; ++r) s[r][c] = _mm512_mask_mov_ps(ninf, keep, s[r][c]);
      }
    }
    const __m512 sc = _mm512_set1_ps(scale);
    for (int r = 0; r < R; ++r) {
      const __m512 mx = _mm512_max_ps(_mm512_max_ps(s[r][0], s[r][1]), _mm512_max_ps(s[r][2], s[r][3]));
      const float bmax = _mm512_reduce_max_ps(mx) * scale;  // scale > 0: max commutes with it
      const float mnew = bmax > m[r] ? bmax : m[r];
      // exp(m_old - m_new); m_old = -inf on the first block gives exp(-inf) -> 0 (clamped)
      alpha[r] = _mm512_cvtss_f32(exp_ps(_mm512_set1_ps(m[r] - mnew)));
      m[r] = mnew;
      const __m512 mb = _mm512_set1_ps(mnew);
      __m512 p[4];
      for (int c = 0; c < 4; ++c) p[c] = exp_ps(_mm512_fmsub_ps(s[r][c], sc, mb));
      const __m512 psum = _mm512_add_ps(_mm512_add_ps(p[0], p[1]), _mm512_add_ps(p[2], p[3]));
      l[r] = _mm512_fmadd_ps(l[r], _mm512_set1_ps(alpha[r]), psum);
      // natural key order: lanes 0-15 of cvtne2ps_pbh(a, b) come from b
      _mm512_store_si512(pbuf + r * KB, (__m512i)_mm512_cvtne2ps_pbh(p[1], p[0]));
      _mm512_store_si512(pbuf + r * KB + 32, (__m512i)_mm512_cvtne2ps_pbh(p[3], p[2]));
    }
  }
  const int npairs = (nk + 1) / 2;  // pairs past that hold only padding (P = 0, V = 0)
  int c0 = 0;
  for (; c0 + 4 <= D / 16; c0 += 4) pv_chunk<D, R, 4>(vblk, pbuf, npairs, alpha, o, c0);
  if (c0 < D / 16) pv_chunk<D, R, 2>(vblk, pbuf, npairs, alpha, o, c0);  // D % 64 == 32
}

template <int D>
void run_task(int64_t task, int64_t H, int64_t N, const uint16_t* q, const uint16_t* kp,
              const uint16_t* vp, uint16_t* out) {
  const int64_t nqb = (N + MQ - 1) / MQ;
  const int64_t np = (N + KB - 1) / KB * KB;
  const int64_t bh = task / nqb, row0 = (task % nqb) * MQ;
  const int64_t b = bh / H, h = bh % H;
  const int nrows = (int)(N - row0 < MQ ? N - row0 : MQ);
  const uint16_t* qb = q + (bh * N + row0) * D;
  const uint16_t* kb = kp + bh * np * D;
  const uint16_t* vb = vp + bh * np * D;
  const float scale = 1.0f / __builtin_sqrtf((float)D);

  alignas(64) float o[MQ * D];
  float m[MQ];
  __m512 l[MQ];
  for (int i = 0; i < MQ * D; ++i) o[i] = 0.0f;
  for (int r = 0; r < MQ; ++r) {
    m[r] = -std::numeric_limits<float>::infinity();
    l[r] = _mm512_setzero_ps();
  }
  for (int64_t k0 = 0; k0 < N; k0 += KB) {
    const int nk = (int)(N - k0 < KB ? N - k0 : KB);
    // a block of KB keys starts KB * D elements further in both packed layouts
    const uint16_t* kblk = kb + k0 * D;
    const uint16_t* vblk = vb + k0 * D;
    int r0 = 0;
    for (; r0 + MR <= nrows; r0 += MR)
      tile<D, MR>(qb + r0 * D, kblk, vblk, nk, scale, m + r0, l + r0, o + r0 * D);
    switch (nrows - r0) {
      case 5: tile<D, 5>(qb + r0 * D, kblk, vblk, nk, scale, m + r0, l + r0, o + r0 * D); break;
      case 4: tile<D, 4>(qb + r0 * D, kblk, vblk, nk, scale, m + r0, l + r0, o + r0 * D); break;
      case 3: tile<D, 3>(qb + r0 * D, kblk, vblk, nk, scale, m + r0, l + r0, o + r0 * D); break;
      case 2: tile<D, 2>(qb + r0 * D, kblk, vblk, nk, scale, m + r0, l + r0, o + r0 * D); break;
      case 1: tile<D, 1>(qb + r0 * D, kblk, vblk, nk, scale, m + r0, l + r0, o + r0 * D); break;
      default: break;
    }
  }
  for (int r = 0; r < nrows; ++r) {
    const float sum = _mm512_reduce_add_ps(l[r]);  // >= 1: the max's own term is exp(0)
    const __m512 inv = _mm512_set1_ps(1.0f / sum);
    uint16_t* dst = out + ((b * N + row0 + r) * H + h) * D;
    for (int c = 0; c < D / 16; ++c) {
      const __m256bh y = _mm512_cvtneps_pbh(_mm512_mul_ps(_mm512_loadu_ps(o + r * D + 16 * c), inv));
      _mm256_storeu_si256((__m256i*)(dst + 16 * c), (__m256i)y);
    }
  }
}

template <int D>
void run_all(int64_t B, int64_t H, int64_t N, const uint16_t* q, const uint16_t* kp, const uint16_t* vp,
             uint16_t* out, int64_t* counter) {
  const int64_t ntasks = B * H * ((N + MQ - 1) / MQ);
  for (;;) {
    const int64_t t = __atomic_fetch_add(counter, 1, __ATOMIC_RELAXED);
    if (t >= ntasks) break;
    run_task<D>(t, H, N, q, kp, vp, out);
  }
}

}  // namespace

extern "C" {

int vggt_attn_abi_version() { return 1; }

// 1 when the running CPU has the instructions this library was compiled for.
int vggt_attn_cpu_ok() {
  __builtin_cpu_init();
  return __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512bw") &&
         __builtin_cpu_supports("avx512vl") && __builtin_cpu_supports("avx512bf16");
}

int vggt_attn_key_block() { return KB; }

// y[i] = exp(x[i]) through the kernel's vectorised exp (for tests); n >= 0.
void vggt_attn_exp(const float* x, float* y, int64_t n) {
  int64_t i = 0;
  for (; i + 16 <= n; i += 16) _mm512_storeu_ps(y + i, exp_ps(_mm512_loadu_ps(x + i)));
  if (i < n) {
    const __mmask16 mk = (__mmask16)((1u << (n - i)) - 1u);
    _mm512_mask_storeu_ps(y + i, mk, exp_ps(_mm512_maskz_loadu_ps(mk, x + i)));
  }
}

// Softmax(q k^T / sqrt(D)) v for all (b, h); layouts at the top of the file. Threads calling this
// concurrently with the same counter (initially 0) split the B * nh * ceil(N / 48) tasks.
// Returns 0, or -1 for an unsupported head dim D (32, 64, 96, 128 are supported).
int vggt_attn_bf16(int64_t B, int64_t H, int64_t N, int64_t D, const void* q, const void* kp,
                   const void* vp, void* out, int64_t* counter) {
  const auto* q16 = static_cast<const uint16_t*>(q);
  const auto* k16 = static_cast<const uint16_t*>(kp);
  const auto* v16 = static_cast<const uint16_t*>(vp);
  auto* o16 = static_cast<uint16_t*>(out);
  switch (D) {
    case 32: run_all<32>(B, H, N, q16, k16, v16, o16, counter); return 0;
    case 64: run_all<64>(B, H, N, q16, k16, v16, o16, counter); return 0;
    case 96: run_all<96>(B, H, N, q16, k16, v16, o16, counter); return 0;
    case 128: run_all<128>(B, H, N, q16, k16, v16, o16, counter); return 0;
    default: return -1;
  }
}

}  // extern "C"
