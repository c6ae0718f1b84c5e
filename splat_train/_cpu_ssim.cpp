// SSIM of the 3DGS loss on the CPU: separable Gaussian filtering, forward and backward (issue 15).
//
// Built and loaded like _cpu_kernel.cpp (plain C ABI, ctypes). Semantics of
// splat_train/losses.py ssim_map (the reference): per channel, local statistics with an
// 11 x 11 Gaussian window that is the outer product of a 1D window g (so filtering is a row pass
// then a column pass), zero padding, C1 = 0.01^2, C2 = 0.03^2. Returns the sum of the SSIM
// map per channel; the backward uses that the zero-padded 'same' filter with a symmetric window
// is its own adjoint:
//   m0 = F(a), m1 = F(b), m2 = F(a a), m3 = F(b b), m4 = F(a b)
//   S = (2 m0 m1 + C1)(2 (m4 - m0 m1) + C2) / ((m0^2 + m1^2 + C1)((m2 - m0^2) + (m3 - m1^2) + C2))
//   dL/da = F(G0) + 2 a F(G2) + b F(G4),  G_j = w dS/dm_j
// Planes are [C, H, W] contiguous; one channel per work item from a shared counter (the result
// does not depend on the thread count).

#include <algorithm>
#include <cstdint>
#include <vector>

namespace {

constexpr double C1 = 0.01 * 0.01;
constexpr double C2 = 0.03 * 0.03;

// out = F(in) for one [H, W] plane; tmp is [H, W] scratch. Window of odd size ws.
template <typename T>
void filter_plane(int64_t H, int64_t W, int ws, const T* g, const T* in, T* tmp, T* out) {
  const int r = ws / 2;
  for (int64_t y = 0; y < H; ++y) {
    const T* s = in + y * W;
    T* h = tmp + y * W;
    for (int64_t x = 0; x < W; ++x) {
      if (x >= r && x + r < W) continue;
      T acc = 0;
      for (int k = 0; k < ws; ++k) {
        const int64_t xx = x + k - r;
        if (xx >= 0 && xx < W) acc += g[k] * s[xx];
      }
      h[x] = acc;
    }
    for (int64_t x = r; x + r < W; ++x) {
      T acc = 0;
      for (int k = 0; k < ws; ++k) acc += g[k] * s[x + k - r];
      h[x] = acc;
    }
  }
  for (int64_t y = 0; y < H; ++y) {
    T* o = out + y * W;
    for (int64_t x = 0; x < W; ++x) o[x] = 0;
    for (int k = 0; k < ws; ++k) {
      const int64_t yy = y + k - r;
      if (yy < 0 || yy >= H) continue;
      const T gk = g[k];
      const T* h = tmp + yy * W;
      for (int64_t x = 0; x < W; ++x) o[x] += gk * h[x];
    }
  }
}

// Per channel c: m[c] = 5 filtered planes (kept for the backward), ssim_sum[c] = sum of the map.
template <typename T>
void forward_impl(int64_t C, int64_t H, int64_t W, int ws, const T* g, const T* a, const T* b, T* m,
                  double* ssim_sum, int64_t* next) {
  const int64_t P = H * W;
  std::vector<T> prod(P), tmp(P);
  for (int64_t c; (c = __atomic_fetch_add(next, 1, __ATOMIC_RELAXED)) < C;) {
    const T* ac = a + c * P;
    const T* bc = b + c * P;
    T* mc = m + c * 5 * P;
    filter_plane(H, W, ws, g, ac, tmp.data(), mc);
    filter_plane(H, W, ws, g, bc, tmp.data(), mc + P);
    for (int64_t i = 0; i < P; ++i) prod[i] = ac[i] * ac[i];
    filter_plane(H, W, ws, g, prod.data(), tmp.data(), mc + 2 * P);
    for (int64_t i = 0; i < P; ++i) prod[i] = bc[i] * bc[i];
    filter_plane(H, W, ws, g, prod.data(), tmp.data(), mc + 3 * P);
    for (int64_t i = 0; i < P; ++i) prod[i] = ac[i] * bc[i];
    filter_plane(H, W, ws, g, prod.data(), tmp.data(), mc + 4 * P);
    double total = 0;
    for (int64_t i = 0; i < P; ++i) {
      const T m0 = mc[i], m1 = mc[P + i];
      const T mu1_sq = m0 * m0, mu2_sq = m1 * m1, mu12 = m0 * m1;
      const T s11 = mc[2 * P + i] - mu1_sq, s22 = mc[3 * P + i] - mu2_sq, s12 = mc[4 * P + i] - mu12;
      total += (double)(((T(2) * mu12 + T(C1)) * (T(2) * s12 + T(C2))) /
                        ((mu1_sq + mu2_sq + T(C1)) * (s11 + s22 + T(C2))));
    }
    ssim_sum[c] = total;
  }
}

// da = w * d(sum of the map)/da, from the filtered planes m of the forward.
template <typename T>
void backward_impl(int64_t C, int64_t H, int64_t W, int ws, const T* g, const T* a, const T* b, const T* m,
                   T w, T* da, int64_t* next) {
  const int64_t P = H * W;
  std::vector<T> G(3 * P), F3(3 * P), tmp(P);
  for (int64_t c; (c = __atomic_fetch_add(next, 1, __ATOMIC_RELAXED)) < C;) {
    const T* ac = a + c * P;
    const T* bc = b + c * P;
    const T* mc = m + c * 5 * P;
    for (int64_t i = 0; i < P; ++i) {
      const T m0 = mc[i], m1 = mc[P + i];
      const T A1 = T(2) * m0 * m1 + T(C1);
      const T A2 = T(2) * (mc[4 * P + i] - m0 * m1) + T(C2);
      const T B1 = m0 * m0 + m1 * m1 + T(C1);
      const T B2 = (mc[2 * P + i] - m0 * m0) + (mc[3 * P + i] - m1 * m1) + T(C2);
      const T inv = T(1) / (B1 * B2);
      const T S = A1 * A2 * inv;
      const T dA1 = A2 * inv, dA2 = A1 * inv, dB1 = -S / B1, dB2 = -S / B2;
      G[i] = w * (dA1 * T(2) * m1 - dA2 * T(2) * m1 + dB1 * T(2) * m0 - dB2 * T(2) * m0);
      G[P + i] = w * dB2;
      G[2 * P + i] = w * dA2 * T(2);
    }
    for (int j = 0; j < 3; ++j) filter_plane(H, W, ws, g, G.data() + j * P, tmp.data(), F3.data() + j * P);
    T* dac = da + c * P;
    for (int64_t i = 0; i < P; ++i) dac[i] = F3[i] + T(2) * ac[i] * F3[P + i] + bc[i] * F3[2 * P + i];
  }
}

}  // namespace

extern "C" {

int splat_ssim_abi_version() { return 1; }

void splat_ssim_forward_f32(int64_t C, int64_t H, int64_t W, int64_t ws, const float* g, const float* a,
                            const float* b, float* m, double* sums, int64_t* next) {
  forward_impl<float>(C, H, W, (int)ws, g, a, b, m, sums, next);
}
void splat_ssim_forward_f64(int64_t C, int64_t H, int64_t W, int64_t ws, const double* g, const double* a,
                            const double* b, double* m, double* sums, int64_t* next) {
  forward_impl<double>(C, H, W, (int)ws, g, a, b, m, sums, next);
}
void splat_ssim_backward_f32(int64_t C, int64_t H, int64_t W, int64_t ws, const float* g, const float* a,
                             const float* b, const float* m, double w, float* da, int64_t* next) {
  backward_impl<float>(C, H, W, (int)ws, g, a, b, m, (float)w, da, next);
}
void splat_ssim_backward_f64(int64_t C, int64_t H, int64_t W, int64_t ws, const double* g, const double* a,
                             const double* b, const double* m, double w, double* da, int64_t* next) {
  backward_impl<double>(C, H, W, (int)ws, g, a, b, m, w, da, next);
}

}  // extern "C"
