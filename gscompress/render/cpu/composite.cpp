// Tile-based front-to-back alpha compositing of projected Gaussians: forward and backward.
//
// The rules are those of gscompress/render/torch_backend.py (the oracle these kernels are tested
// against): pixel (i, j) is evaluated at (i, j); alpha = min(0.99, o exp(power)); alpha < 1/255
// is skipped; compositing stops before the Gaussian that would bring T below 1e-4 (that one is
// left out).
//
// Layout of the work: tiles of 16x16 pixels are handed to threads with OpenMP dynamic
// scheduling. Within a tile the loop runs Gaussian by Gaussian (front to back in the forward,
// back to front in the backward); for each Gaussian only the tile rows where its alpha can reach
// 1/255 are visited, and each such row is one branch-free, SIMD-vectorised loop over its 16
// pixels, with per-pixel state (T, accumulated features, ...) in small tile-local arrays.
//
// The forward stores per pixel the final transmittance and the number of list entries it
// consumed, so the backward is a single back-to-front pass that recovers T by division.
// Per-Gaussian sums (contribution, gradients) are reduced over pixels inside the tile, then
// added to thread-local buffers that are summed at the end: no atomics.

#include <torch/extension.h>

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr int kTile = 16;
constexpr int kPix = kTile * kTile;
constexpr int kCh = 4;     // composited features: r, g, b, depth
constexpr int kGrad = 10;  // per-Gaussian gradient slots: mean2d(2) conic(3) opacity(1) feats(4)

template <typename scalar_t>
struct Rules {
  static constexpr scalar_t alpha_max = scalar_t(0.99);
  static constexpr scalar_t alpha_min = scalar_t(1.0 / 255.0);
  static constexpr scalar_t t_min = scalar_t(1e-4);
};

// One tile row of 16 pixels as a GCC vector: the compiler maps it onto whatever SIMD the build
// targets (one AVX-512 register of floats, two AVX2 registers, four SSE registers, ...).
template <typename S>
struct Simd;
template <>
struct Simd<float> {
  typedef float V __attribute__((vector_size(kTile * sizeof(float))));
  typedef int32_t I __attribute__((vector_size(kTile * sizeof(int32_t))));
  typedef int32_t Int;
};
template <>
struct Simd<double> {
  typedef double V __attribute__((vector_size(kTile * sizeof(double))));
  typedef int64_t I __attribute__((vector_size(kTile * sizeof(int64_t))));
  typedef int64_t Int;
};

template <typename V, typename S>
inline V splat(S s) {
  return V{} + s;
}

template <typename V>
inline auto hsum(const V& v) {
  auto sum = v[0];
  for (int i = 1; i < kTile; ++i) sum += v[i];
  return sum;
}

// exp(x) for x <= 0, accurate to about 1 ulp, on a whole row (libm's exp does not vectorise).
// x is clamped at -30: there alpha = o exp(x) is far below 1/255, so the clamp never changes a
// composited value, and it keeps every product in masked-out lanes away from denormals, which
// are very slow to compute with.
constexpr double kMinPower = -30.0;

inline Simd<float>::V vexp(Simd<float>::V x) {
  using V = Simd<float>::V;
  using I = Simd<float>::I;
  x = x < float(kMinPower) ? splat<V>(float(kMinPower)) : x;
  const float big = 12582912.0f;  // 1.5 * 2^23: adding it rounds to an integer
  const V n = (x * 1.44269504088896341f + big) - big;
  V r = x - n * 0.693359375f;
  r = r - n * -2.12194440e-4f;
  V p = splat<V>(1.9875691500e-4f);
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  const V y = p * (r * r) + r + 1.0f;
  const I bits = (__builtin_convertvector(n, I) + 127) << 23;
  return y * reinterpret_cast<const V&>(bits);
}

inline Simd<double>::V vexp(Simd<double>::V x) {
  using V = Simd<double>::V;
  using I = Simd<double>::I;
  x = x < kMinPower ? splat<V>(kMinPower) : x;
  const double big = 6755399441055744.0;  // 1.5 * 2^52
  const V n = (x * 1.4426950408889634 + big) - big;
  V r = x - n * 6.93145751953125e-1;
  r = r - n * 1.42860682030941723212e-6;
  // Taylor series to degree 13 on |r| <= ln(2)/2: truncation error below 1e-17.
  V p = splat<V>(1.0 / 6227020800.0);
  p = p * r + 1.0 / 479001600.0;
  p = p * r + 1.0 / 39916800.0;
  p = p * r + 1.0 / 3628800.0;
  p = p * r + 1.0 / 362880.0;
  p = p * r + 1.0 / 40320.0;
  p = p * r + 1.0 / 5040.0;
  p = p * r + 1.0 / 720.0;
  p = p * r + 1.0 / 120.0;
  p = p * r + 1.0 / 24.0;
  p = p * r + 1.0 / 6.0;
  p = p * r + 0.5;
  const V y = p * (r * r) + r + 1.0;
  const I bits = (__builtin_convertvector(n, I) + 1023) << 52;
  return y * reinterpret_cast<const V&>(bits);
}

// Half extents (x, y) in pixels of the ellipse outside which a Gaussian's alpha is provably
// below 1/255: alpha = o exp(-q / 2) >= 1/255 needs q <= 2 ln(255 o), and on that ellipse |dx|
// is at most sqrt(2 ln(255 o) Sigma_xx), Sigma = conic^-1. A 1e-3 relative + 1e-2 px margin
// keeps rounding from dropping a pixel that the exact test would keep; pixels inside are tested
// exactly. -1 marks a Gaussian that can never reach 1/255; +inf a degenerate conic (test all).
template <typename scalar_t>
void footprints(const scalar_t* conics, const scalar_t* opac, int64_t n, float* extents,
                int n_threads) {
#pragma omp parallel for num_threads(n_threads) schedule(static)
  for (int64_t g = 0; g < n; ++g) {
    const double o = opac[g], a = conics[3 * g], b = conics[3 * g + 1], c = conics[3 * g + 2];
    const double q = 2.0 * std::log(255.0 * o) * 1.001 + 1e-6;
    const double det = a * c - b * b;
    if (!(o >= double(Rules<scalar_t>::alpha_min))) {
      extents[2 * g] = extents[2 * g + 1] = -1.0f;
    } else if (!(q > 0.0) || !(det > 0.0) || !(a > 0.0) || !(c > 0.0)) {
      extents[2 * g] = extents[2 * g + 1] = INFINITY;
    } else {
      extents[2 * g] = float(std::sqrt(q * c / det) + 1e-2);
      extents[2 * g + 1] = float(std::sqrt(q * a / det) + 1e-2);
    }
  }
}

// Range [lo, hi) of tile-local coordinates within `half` of `centre` (tile starts at `origin`).
inline void span(double centre, float half, int origin, int size, int& lo, int& hi) {
  const double l = std::ceil(centre - double(half)) - origin;
  const double h = std::floor(centre + double(half)) - origin + 1;
  lo = int(std::clamp(l, 0.0, double(size)));
  hi = int(std::clamp(h, 0.0, double(size)));
}

// Everything the per-row loops need about one Gaussian in one tile.
template <typename scalar_t>
struct Splat {
  scalar_t mx, my, a, b, c, o, f[kCh];
  int x0, x1, y0, y1;  // tile-local rows / columns where alpha can reach 1/255

  // Loads Gaussian g; false when it cannot reach 1/255 anywhere in this tile.
  bool load(int64_t g, const scalar_t* means2d, const scalar_t* conics, const scalar_t* opac,
            const scalar_t* feats, const float* extents, int tile_x, int tile_y, int tw,
            int th) {
    if (extents[2 * g] < 0) return false;
    mx = means2d[2 * g];
    my = means2d[2 * g + 1];
    span(mx, extents[2 * g], tile_x, tw, x0, x1);
    span(my, extents[2 * g + 1], tile_y, th, y0, y1);
    if (x0 >= x1 || y0 >= y1) return false;
    a = conics[3 * g];
    b = conics[3 * g + 1];
    c = conics[3 * g + 2];
    o = opac[g];
    for (int ch = 0; ch < kCh; ++ch) f[ch] = feats[kCh * g + ch];
    return true;
  }
};

template <typename scalar_t>
void forward_impl(const scalar_t* means2d, const scalar_t* conics, const scalar_t* opac,
                  const scalar_t* feats, const int64_t* offsets, const int64_t* ids, int64_t n,
                  int width, int height, int tiles_x, int tiles_y, scalar_t* out_feats,
                  scalar_t* out_T, int32_t* out_last, scalar_t* contrib, int n_threads) {
  using R = Rules<scalar_t>;
  using V = typename Simd<scalar_t>::V;
  using I = typename Simd<scalar_t>::I;
  using int_t = typename Simd<scalar_t>::Int;
  const int n_tiles = tiles_x * tiles_y;
  std::vector<float> extents(size_t(2) * n);
  footprints(conics, opac, n, extents.data(), n_threads);
  std::vector<scalar_t> contrib_local(contrib ? size_t(n_threads) * n : 0, scalar_t(0));

#pragma omp parallel num_threads(n_threads)
  {
    scalar_t* my_contrib =
        contrib ? contrib_local.data() + size_t(omp_get_thread_num()) * n : nullptr;
    // Per-pixel state, one vector per tile row.
    V T[kTile];
    V acc[kCh][kTile];
    I alive[kTile];  // all ones while the pixel is still compositing
    I last[kTile];   // list entries consumed (index of the last composited one + 1)
    V lane;
    for (int lx = 0; lx < kTile; ++lx) lane[lx] = scalar_t(lx);

#pragma omp for schedule(dynamic, 1)
    for (int t = 0; t < n_tiles; ++t) {
      const int tile_x = (t % tiles_x) * kTile, tile_y = (t / tiles_x) * kTile;
      const int tw = std::min(kTile, width - tile_x), th = std::min(kTile, height - tile_y);
      const V xs = lane + scalar_t(tile_x);
      for (int ly = 0; ly < kTile; ++ly) {
        T[ly] = splat<V>(scalar_t(1));
        for (int ch = 0; ch < kCh; ++ch) acc[ch][ly] = V{};
        alive[ly] = (lane < scalar_t(tw)) & splat<I>(int_t(ly < th ? -1 : 0));
        last[ly] = I{};
      }
      int n_active = tw * th;
      const int64_t begin = offsets[t], end = offsets[t + 1];
      Splat<scalar_t> sp;

      for (int64_t s = begin; s < end && n_active > 0; ++s) {
        const int64_t g = ids[s];
        if (!sp.load(g, means2d, conics, opac, feats, extents.data(), tile_x, tile_y, tw, th))
          continue;
        const I k1 = splat<I>(int_t(s - begin + 1));
        const I in_x = (xs > scalar_t(tile_x + sp.x0) - scalar_t(0.5)) &
                       (xs < scalar_t(tile_x + sp.x1) - scalar_t(0.5));
        const V dx = xs - sp.mx;
        const V a_dx_dx = sp.a * dx * dx;
        V lane_w{};
        I lane_stop{};
        for (int ly = sp.y0; ly < sp.y1; ++ly) {
          const scalar_t dy = scalar_t(tile_y + ly) - sp.my;
          // Same operation order as the torch oracle, so both round alike.
          const V power = scalar_t(-0.5) * (a_dx_dx + sp.c * dy * dy) - sp.b * dx * dy;
          const V oG = sp.o * vexp(power);
          const V alpha = oG > R::alpha_max ? splat<V>(R::alpha_max) : oG;
          const V Tp = T[ly];
          const V T_next = Tp * (scalar_t(1) - alpha);
          const I hit = in_x & alive[ly] & (alpha >= R::alpha_min);
          const I stop = hit & (T_next < R::t_min);
          const I use = hit & ~stop;
          const V w = use ? alpha * Tp : V{};
          for (int ch = 0; ch < kCh; ++ch) acc[ch][ly] += w * sp.f[ch];
          T[ly] = use ? T_next : Tp;
          last[ly] = use ? k1 : last[ly];
          alive[ly] &= ~stop;
          lane_w += w;
          lane_stop -= stop;  // stop is -1 where a pixel stops
        }
        n_active -= int(hsum(lane_stop));
        if (my_contrib) my_contrib[g] += hsum(lane_w);
      }

      for (int ly = 0; ly < th; ++ly) {
        for (int lx = 0; lx < tw; ++lx) {
          const int64_t q = int64_t(tile_y + ly) * width + (tile_x + lx);
          for (int ch = 0; ch < kCh; ++ch) out_feats[kCh * q + ch] = acc[ch][ly][lx];
          out_T[q] = T[ly][lx];
          out_last[q] = int32_t(last[ly][lx]);
        }
      }
    }

    if (contrib) {
#pragma omp for schedule(static)
      for (int64_t g = 0; g < n; ++g) {
        scalar_t sum = 0;
        for (int k = 0; k < n_threads; ++k) sum += contrib_local[size_t(k) * n + g];
        contrib[g] = sum;
      }
    }
  }
}

template <typename scalar_t>
void backward_impl(const scalar_t* means2d, const scalar_t* conics, const scalar_t* opac,
                   const scalar_t* feats, const int64_t* offsets, const int64_t* ids, int64_t n,
                   int width, int height, int tiles_x, int tiles_y, const scalar_t* T_final,
                   const int32_t* last_in, const scalar_t* grad_feats, const scalar_t* grad_T,
                   scalar_t* g_means2d, scalar_t* g_conics, scalar_t* g_opac, scalar_t* g_feats,
                   int n_threads) {
  using R = Rules<scalar_t>;
  using V = typename Simd<scalar_t>::V;
  using I = typename Simd<scalar_t>::I;
  using int_t = typename Simd<scalar_t>::Int;
  const int n_tiles = tiles_x * tiles_y;
  std::vector<float> extents(size_t(2) * n);
  footprints(conics, opac, n, extents.data(), n_threads);
  std::vector<scalar_t> local(size_t(n_threads) * n * kGrad, scalar_t(0));

#pragma omp parallel num_threads(n_threads)
  {
    scalar_t* mine = local.data() + size_t(omp_get_thread_num()) * n * kGrad;
    // Per-pixel state, one vector per tile row.
    V T[kTile];         // transmittance after the current Gaussian
    V gT_end[kTile];    // dL/dT_final * T_final
    V gF[kCh][kTile];   // dL/d(composited features)
    V S[kCh][kTile];    // sum over the Gaussians behind of w_j f_j
    I last[kTile];      // list entries consumed by the pixel in the forward
    V lane;
    for (int lx = 0; lx < kTile; ++lx) lane[lx] = scalar_t(lx);

#pragma omp for schedule(dynamic, 1)
    for (int t = 0; t < n_tiles; ++t) {
      const int tile_x = (t % tiles_x) * kTile, tile_y = (t / tiles_x) * kTile;
      const int tw = std::min(kTile, width - tile_x), th = std::min(kTile, height - tile_y);
      const V xs = lane + scalar_t(tile_x);
      int32_t k_max = 0;
      for (int ly = 0; ly < kTile; ++ly) {
        T[ly] = splat<V>(scalar_t(1));
        gT_end[ly] = V{};
        last[ly] = I{};
        for (int ch = 0; ch < kCh; ++ch) gF[ch][ly] = S[ch][ly] = V{};
        for (int lx = 0; lx < tw && ly < th; ++lx) {
          const int64_t q = int64_t(tile_y + ly) * width + (tile_x + lx);
          T[ly][lx] = T_final[q];
          gT_end[ly][lx] = grad_T[q] * T_final[q];
          for (int ch = 0; ch < kCh; ++ch) gF[ch][ly][lx] = grad_feats[kCh * q + ch];
          last[ly][lx] = last_in[q];
          k_max = std::max(k_max, last_in[q]);
        }
      }
      const int64_t begin = offsets[t];
      Splat<scalar_t> sp;

      for (int64_t s = begin + k_max - 1; s >= begin; --s) {
        const int64_t g = ids[s];
        if (!sp.load(g, means2d, conics, opac, feats, extents.data(), tile_x, tile_y, tw, th))
          continue;
        const I k = splat<I>(int_t(s - begin));
        const I in_x = (xs > scalar_t(tile_x + sp.x0) - scalar_t(0.5)) &
                       (xs < scalar_t(tile_x + sp.x1) - scalar_t(0.5));
        const V dx = xs - sp.mx;
        const V a_dx_dx = sp.a * dx * dx;
        const V a_dx = sp.a * dx, b_dx = sp.b * dx;
        // Per-lane partial gradients, summed over the lanes once per Gaussian.
        V d_mx{}, d_my{}, d_a{}, d_b{}, d_c{}, d_o{};
        V d_f[kCh] = {};
        for (int ly = sp.y0; ly < sp.y1; ++ly) {
          const scalar_t dy = scalar_t(tile_y + ly) - sp.my;
          const V power = scalar_t(-0.5) * (a_dx_dx + sp.c * dy * dy) - sp.b * dx * dy;
          const V G = vexp(power);
          const V oG = sp.o * G;
          const V alpha = oG > R::alpha_max ? splat<V>(R::alpha_max) : oG;
          const I hit = in_x & (k < last[ly]) & (alpha >= R::alpha_min);
          const V one_minus = scalar_t(1) - alpha;
          const V T_before = T[ly] / one_minus;
          const V w = hit ? alpha * T_before : V{};
          // dL/dalpha: this Gaussian's own term, minus what it hides behind it, minus its
          // share of the final transmittance.
          V own{}, behind = gT_end[ly];
          for (int ch = 0; ch < kCh; ++ch) {
            own += gF[ch][ly] * sp.f[ch];
            behind += gF[ch][ly] * S[ch][ly];
            d_f[ch] += w * gF[ch][ly];
            S[ch][ly] += w * sp.f[ch];
          }
          T[ly] = hit ? T_before : T[ly];
          // The clamp at 0.99 passes no gradient once it bites.
          const I pass = hit & (oG <= R::alpha_max);
          const V d_alpha = pass ? T_before * own - behind / one_minus : V{};
          d_o += d_alpha * G;
          const V d_pow = d_alpha * alpha;
          d_a += scalar_t(-0.5) * d_pow * dx * dx;
          d_b -= d_pow * dx * dy;
          d_c += scalar_t(-0.5) * d_pow * dy * dy;
          d_mx += d_pow * (a_dx + sp.b * dy);
          d_my += d_pow * (b_dx + sp.c * dy);
        }
        scalar_t* dst = mine + size_t(g) * kGrad;
        dst[0] += hsum(d_mx);
        dst[1] += hsum(d_my);
        dst[2] += hsum(d_a);
        dst[3] += hsum(d_b);
        dst[4] += hsum(d_c);
        dst[5] += hsum(d_o);
        for (int ch = 0; ch < kCh; ++ch) dst[6 + ch] += hsum(d_f[ch]);
      }
    }

#pragma omp for schedule(static)
    for (int64_t g = 0; g < n; ++g) {
      scalar_t sum[kGrad] = {0};
      for (int k = 0; k < n_threads; ++k) {
        const scalar_t* src = local.data() + (size_t(k) * n + g) * kGrad;
        for (int j = 0; j < kGrad; ++j) sum[j] += src[j];
      }
      g_means2d[2 * g] = sum[0];
      g_means2d[2 * g + 1] = sum[1];
      g_conics[3 * g] = sum[2];
      g_conics[3 * g + 1] = sum[3];
      g_conics[3 * g + 2] = sum[4];
      g_opac[g] = sum[5];
      for (int ch = 0; ch < kCh; ++ch) g_feats[kCh * g + ch] = sum[6 + ch];
    }
  }
}

void check_inputs(const torch::Tensor& means2d, const torch::Tensor& conics,
                  const torch::Tensor& opac, const torch::Tensor& feats,
                  const torch::Tensor& offsets, const torch::Tensor& ids, int64_t tiles_x,
                  int64_t tiles_y) {
  const auto n = means2d.size(0);
  TORCH_CHECK(means2d.dim() == 2 && means2d.size(1) == 2, "means2d must be [N, 2]");
  TORCH_CHECK(conics.dim() == 2 && conics.size(0) == n && conics.size(1) == 3,
              "conics must be [N, 3]");
  TORCH_CHECK(opac.dim() == 1 && opac.size(0) == n, "opacities must be [N]");
  TORCH_CHECK(feats.dim() == 2 && feats.size(0) == n && feats.size(1) == kCh,
              "features must be [N, 4]");
  TORCH_CHECK(offsets.dim() == 1 && offsets.size(0) == tiles_x * tiles_y + 1,
              "offsets must be [tiles + 1]");
  TORCH_CHECK(offsets.scalar_type() == torch::kInt64 && ids.scalar_type() == torch::kInt64,
              "offsets and ids must be int64");
  for (const auto* x : {&means2d, &conics, &opac, &feats}) {
    TORCH_CHECK(x->scalar_type() == means2d.scalar_type(), "all inputs must share a dtype");
    TORCH_CHECK(x->is_contiguous() && x->device().is_cpu(), "inputs must be contiguous CPU");
  }
  TORCH_CHECK(offsets.is_contiguous() && ids.is_contiguous(), "bins must be contiguous");
}

std::vector<torch::Tensor> composite_forward(torch::Tensor means2d, torch::Tensor conics,
                                             torch::Tensor opac, torch::Tensor feats,
                                             torch::Tensor offsets, torch::Tensor ids,
                                             int64_t width, int64_t height, int64_t tiles_x,
                                             int64_t tiles_y, bool want_contribution) {
  check_inputs(means2d, conics, opac, feats, offsets, ids, tiles_x, tiles_y);
  const auto n = means2d.size(0);
  auto opts = means2d.options();
  auto out_feats = torch::empty({height, width, kCh}, opts);
  auto out_T = torch::empty({height, width}, opts);
  auto out_last = torch::empty({height, width}, opts.dtype(torch::kInt32));
  auto contrib = want_contribution ? torch::empty({n}, opts) : torch::empty({0}, opts);
  const int n_threads = std::max(1, at::get_num_threads());
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "composite_forward", [&] {
    forward_impl<scalar_t>(means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
                           opac.data_ptr<scalar_t>(), feats.data_ptr<scalar_t>(),
                           offsets.data_ptr<int64_t>(), ids.data_ptr<int64_t>(), n, int(width),
                           int(height), int(tiles_x), int(tiles_y),
                           out_feats.data_ptr<scalar_t>(), out_T.data_ptr<scalar_t>(),
                           out_last.data_ptr<int32_t>(),
                           want_contribution ? contrib.data_ptr<scalar_t>() : nullptr,
                           n_threads);
  });
  return {out_feats, out_T, out_last, contrib};
}

std::vector<torch::Tensor> composite_backward(torch::Tensor means2d, torch::Tensor conics,
                                              torch::Tensor opac, torch::Tensor feats,
                                              torch::Tensor offsets, torch::Tensor ids,
                                              int64_t width, int64_t height, int64_t tiles_x,
                                              int64_t tiles_y, torch::Tensor T_final,
                                              torch::Tensor last, torch::Tensor grad_feats,
                                              torch::Tensor grad_T) {
  check_inputs(means2d, conics, opac, feats, offsets, ids, tiles_x, tiles_y);
  TORCH_CHECK(T_final.is_contiguous() && last.is_contiguous() && grad_feats.is_contiguous() &&
                  grad_T.is_contiguous(),
              "saved tensors and gradients must be contiguous");
  TORCH_CHECK(last.scalar_type() == torch::kInt32, "last must be int32");
  TORCH_CHECK(grad_feats.scalar_type() == means2d.scalar_type() &&
                  grad_T.scalar_type() == means2d.scalar_type(),
              "gradients must share the input dtype");
  const auto n = means2d.size(0);
  auto g_means2d = torch::empty_like(means2d);
  auto g_conics = torch::empty_like(conics);
  auto g_opac = torch::empty_like(opac);
  auto g_feats = torch::empty_like(feats);
  const int n_threads = std::max(1, at::get_num_threads());
  AT_DISPATCH_FLOATING_TYPES(means2d.scalar_type(), "composite_backward", [&] {
    backward_impl<scalar_t>(
        means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(), opac.data_ptr<scalar_t>(),
        feats.data_ptr<scalar_t>(), offsets.data_ptr<int64_t>(), ids.data_ptr<int64_t>(), n,
        int(width), int(height), int(tiles_x), int(tiles_y), T_final.data_ptr<scalar_t>(),
        last.data_ptr<int32_t>(), grad_feats.data_ptr<scalar_t>(), grad_T.data_ptr<scalar_t>(),
        g_means2d.data_ptr<scalar_t>(), g_conics.data_ptr<scalar_t>(),
        g_opac.data_ptr<scalar_t>(), g_feats.data_ptr<scalar_t>(), n_threads);
  });
  return {g_means2d, g_conics, g_opac, g_feats};
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "gscompress tile compositing kernels (forward and backward)";
  m.def("composite_forward", &composite_forward, "front-to-back compositing");
  m.def("composite_backward", &composite_backward, "back-to-front gradients");
}
