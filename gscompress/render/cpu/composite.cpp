// Tile-based front-to-back alpha compositing of projected Gaussians: forward and backward.
//
// The rules are those of gscompress/render/torch_backend.py (the oracle these kernels are tested
// against): pixel (i, j) is evaluated at (i, j); alpha = min(0.99, o exp(power)); alpha < 1/255
// is skipped; compositing stops before the Gaussian that would bring T below 1e-4 (that one is
// left out). Work is split per 16x16 tile with OpenMP dynamic scheduling. Within a tile the loop
// runs Gaussian by Gaussian (front to back) over the pixels of that Gaussian's footprint, so each
// Gaussian only visits the pixels where its alpha can reach 1/255.
//
// The forward stores per pixel the final transmittance and the number of list entries it
// consumed, so the backward is a single back-to-front pass that recovers T by division.
// Per-Gaussian sums (contribution, gradients) go to thread-local buffers that are reduced at
// the end: no atomics, and a fixed reduction order.

#include <torch/extension.h>

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr int kTile = 16;
constexpr int kPix = kTile * kTile;
constexpr int kCh = 4;      // composited features: r, g, b, depth
constexpr int kGrad = 10;   // per-Gaussian gradient slots: mean2d(2) conic(3) opacity(1) feats(4)

template <typename scalar_t>
struct Rules {
  static constexpr scalar_t alpha_max = scalar_t(0.99);
  static constexpr scalar_t alpha_min = scalar_t(1.0 / 255.0);
  static constexpr scalar_t t_min = scalar_t(1e-4);
};

// Pixel range [lo, hi) of the tile outside which a Gaussian's alpha is provably below 1/255.
// alpha = o exp(-q / 2) >= 1/255 needs q <= 2 ln(255 o), and on that ellipse |dx| is at most
// sqrt(2 ln(255 o) Sigma_xx) with Sigma = conic^-1. The 1e-3 relative + 1e-2 px margin keeps
// rounding from ever dropping a pixel the exact test would keep; those pixels are tested exactly.
struct Span {
  int x0, x1, y0, y1;
};

template <typename scalar_t>
inline Span footprint(scalar_t mx, scalar_t my, scalar_t a, scalar_t b, scalar_t c, scalar_t o,
                      int tile_x, int tile_y, int tw, int th) {
  const double q = 2.0 * std::log(255.0 * double(o)) * 1.001 + 1e-6;
  const double det = double(a) * double(c) - double(b) * double(b);
  Span s{0, 0, 0, 0};
  if (!(q > 0.0) || !(det > 0.0)) {
    // Degenerate input: fall back to testing the whole tile.
    s.x1 = tw;
    s.y1 = th;
    return s;
  }
  const double ex = std::sqrt(q * double(c) / det) + 1e-2;
  const double ey = std::sqrt(q * double(a) / det) + 1e-2;
  const double lx = std::ceil(double(mx) - ex) - tile_x;
  const double hx = std::floor(double(mx) + ex) - tile_x + 1;
  const double ly = std::ceil(double(my) - ey) - tile_y;
  const double hy = std::floor(double(my) + ey) - tile_y + 1;
  s.x0 = int(std::clamp(lx, 0.0, double(tw)));
  s.x1 = int(std::clamp(hx, 0.0, double(tw)));
  s.y0 = int(std::clamp(ly, 0.0, double(th)));
  s.y1 = int(std::clamp(hy, 0.0, double(th)));
  return s;
}

template <typename scalar_t>
inline scalar_t gauss_power(scalar_t a, scalar_t b, scalar_t c, scalar_t dx, scalar_t dy) {
  // Same operation order as the torch oracle, so both round alike.
  return scalar_t(-0.5) * (a * dx * dx + c * dy * dy) - b * dx * dy;
}

template <typename scalar_t>
void forward_impl(const scalar_t* means2d, const scalar_t* conics, const scalar_t* opac,
                  const scalar_t* feats, const int64_t* offsets, const int64_t* ids, int64_t n,
                  int width, int height, int tiles_x, int tiles_y, scalar_t* out_feats,
                  scalar_t* out_T, int32_t* out_last, scalar_t* contrib, int n_threads) {
  using R = Rules<scalar_t>;
  const int n_tiles = tiles_x * tiles_y;
  std::vector<scalar_t> contrib_local(contrib ? size_t(n_threads) * n : 0, scalar_t(0));

#pragma omp parallel num_threads(n_threads)
  {
    scalar_t* my_contrib = contrib ? contrib_local.data() + size_t(omp_get_thread_num()) * n
                                   : nullptr;
    alignas(64) scalar_t T[kPix];
    alignas(64) scalar_t acc[kCh][kPix];
    alignas(64) int32_t last[kPix];
    alignas(64) unsigned char done[kPix];

#pragma omp for schedule(dynamic, 1)
    for (int t = 0; t < n_tiles; ++t) {
      const int tile_x = (t % tiles_x) * kTile, tile_y = (t / tiles_x) * kTile;
      const int tw = std::min(kTile, width - tile_x), th = std::min(kTile, height - tile_y);
      std::fill(T, T + kPix, scalar_t(1));
      std::fill(&acc[0][0], &acc[0][0] + kCh * kPix, scalar_t(0));
      std::fill(last, last + kPix, 0);
      std::fill(done, done + kPix, 0);
      int n_active = tw * th;
      const int64_t begin = offsets[t], end = offsets[t + 1];

      for (int64_t s = begin; s < end && n_active > 0; ++s) {
        const int64_t g = ids[s];
        const scalar_t o = opac[g];
        if (o < R::alpha_min) continue;  // alpha <= o everywhere
        const scalar_t mx = means2d[2 * g], my = means2d[2 * g + 1];
        const scalar_t a = conics[3 * g], b = conics[3 * g + 1], c = conics[3 * g + 2];
        const scalar_t f0 = feats[kCh * g], f1 = feats[kCh * g + 1];
        const scalar_t f2 = feats[kCh * g + 2], f3 = feats[kCh * g + 3];
        const Span sp = footprint(mx, my, a, b, c, o, tile_x, tile_y, tw, th);
        const int32_t k1 = int32_t(s - begin + 1);
        scalar_t csum = 0;
        for (int ly = sp.y0; ly < sp.y1; ++ly) {
          const scalar_t dy = scalar_t(tile_y + ly) - my;
          for (int lx = sp.x0; lx < sp.x1; ++lx) {
            const int p = ly * kTile + lx;
            if (done[p]) continue;
            const scalar_t dx = scalar_t(tile_x + lx) - mx;
            const scalar_t alpha =
                std::min(R::alpha_max, o * std::exp(gauss_power(a, b, c, dx, dy)));
            if (alpha < R::alpha_min) continue;
            const scalar_t Tp = T[p];
            const scalar_t T_next = Tp * (scalar_t(1) - alpha);
            if (T_next < R::t_min) {
              done[p] = 1;
              --n_active;
              continue;
            }
            const scalar_t w = alpha * Tp;
            acc[0][p] += w * f0;
            acc[1][p] += w * f1;
            acc[2][p] += w * f2;
            acc[3][p] += w * f3;
            T[p] = T_next;
            last[p] = k1;
            csum += w;
          }
        }
        if (my_contrib) my_contrib[g] += csum;
      }

      for (int ly = 0; ly < th; ++ly) {
        for (int lx = 0; lx < tw; ++lx) {
          const int p = ly * kTile + lx;
          const int64_t q = int64_t(tile_y + ly) * width + (tile_x + lx);
          for (int ch = 0; ch < kCh; ++ch) out_feats[kCh * q + ch] = acc[ch][p];
          out_T[q] = T[p];
          out_last[q] = last[p];
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
  const int n_tiles = tiles_x * tiles_y;
  std::vector<scalar_t> local(size_t(n_threads) * n * kGrad, scalar_t(0));

#pragma omp parallel num_threads(n_threads)
  {
    scalar_t* my = local.data() + size_t(omp_get_thread_num()) * n * kGrad;
    alignas(64) scalar_t T[kPix];       // transmittance after the current Gaussian
    alignas(64) scalar_t T_end[kPix];   // final transmittance
    alignas(64) scalar_t gT[kPix];      // dL/dT_final
    alignas(64) scalar_t gF[kCh][kPix]; // dL/d(composited features)
    alignas(64) scalar_t S[kCh][kPix];  // sum over the Gaussians behind of w_j f_j
    alignas(64) int32_t last[kPix];

#pragma omp for schedule(dynamic, 1)
    for (int t = 0; t < n_tiles; ++t) {
      const int tile_x = (t % tiles_x) * kTile, tile_y = (t / tiles_x) * kTile;
      const int tw = std::min(kTile, width - tile_x), th = std::min(kTile, height - tile_y);
      std::fill(last, last + kPix, 0);
      int32_t k_max = 0;
      for (int ly = 0; ly < th; ++ly) {
        for (int lx = 0; lx < tw; ++lx) {
          const int p = ly * kTile + lx;
          const int64_t q = int64_t(tile_y + ly) * width + (tile_x + lx);
          T[p] = T_end[p] = T_final[q];
          gT[p] = grad_T[q];
          for (int ch = 0; ch < kCh; ++ch) {
            gF[ch][p] = grad_feats[kCh * q + ch];
            S[ch][p] = 0;
          }
          last[p] = last_in[q];
          k_max = std::max(k_max, last[p]);
        }
      }
      const int64_t begin = offsets[t];

      for (int64_t s = begin + k_max - 1; s >= begin; --s) {
        const int32_t k = int32_t(s - begin);
        const int64_t g = ids[s];
        const scalar_t o = opac[g];
        if (o < R::alpha_min) continue;
        const scalar_t mx = means2d[2 * g], my_ = means2d[2 * g + 1];
        const scalar_t a = conics[3 * g], b = conics[3 * g + 1], c = conics[3 * g + 2];
        const scalar_t f[kCh] = {feats[kCh * g], feats[kCh * g + 1], feats[kCh * g + 2],
                                 feats[kCh * g + 3]};
        const Span sp = footprint(mx, my_, a, b, c, o, tile_x, tile_y, tw, th);
        scalar_t d_mx = 0, d_my = 0, d_a = 0, d_b = 0, d_c = 0, d_o = 0;
        scalar_t d_f[kCh] = {0, 0, 0, 0};
        for (int ly = sp.y0; ly < sp.y1; ++ly) {
          const scalar_t dy = scalar_t(tile_y + ly) - my_;
          for (int lx = sp.x0; lx < sp.x1; ++lx) {
            const int p = ly * kTile + lx;
            if (k >= last[p]) continue;
            const scalar_t dx = scalar_t(tile_x + lx) - mx;
            const scalar_t G = std::exp(gauss_power(a, b, c, dx, dy));
            const scalar_t oG = o * G;
            const scalar_t alpha = std::min(R::alpha_max, oG);
            if (alpha < R::alpha_min) continue;
            const scalar_t one_minus = scalar_t(1) - alpha;
            const scalar_t T_before = T[p] / one_minus;
            const scalar_t w = alpha * T_before;
            scalar_t d_alpha = -gT[p] * T_end[p] / one_minus;
            for (int ch = 0; ch < kCh; ++ch) {
              d_f[ch] += w * gF[ch][p];
              d_alpha += gF[ch][p] * (T_before * f[ch] - S[ch][p] / one_minus);
              S[ch][p] += w * f[ch];
            }
            T[p] = T_before;
            if (oG <= R::alpha_max) {  // the clamp passes no gradient once it bites
              d_o += d_alpha * G;
              const scalar_t d_pow = d_alpha * alpha;
              d_a += scalar_t(-0.5) * d_pow * dx * dx;
              d_b -= d_pow * dx * dy;
              d_c += scalar_t(-0.5) * d_pow * dy * dy;
              d_mx += d_pow * (a * dx + b * dy);
              d_my += d_pow * (b * dx + c * dy);
            }
          }
        }
        scalar_t* dst = my + size_t(g) * kGrad;
        dst[0] += d_mx;
        dst[1] += d_my;
        dst[2] += d_a;
        dst[3] += d_b;
        dst[4] += d_c;
        dst[5] += d_o;
        for (int ch = 0; ch < kCh; ++ch) dst[6 + ch] += d_f[ch];
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
