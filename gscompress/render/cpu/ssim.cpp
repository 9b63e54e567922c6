// SSIM for the mapping loss: the separable 'valid' Gaussian filter of `gscompress.metrics.blur`
// with its backward, and the mean SSIM of `gscompress.metrics.ssim_maps` fused around it.
//
// The filter maps x [C, H, W] -> [C, H - K + 1, W - K + 1]: each channel filtered along its rows
// (W) with the K taps k, then along its columns (H), as the two grouped convolutions of the torch
// version do. Its backward is the transposed filter, columns first, then rows. Both passes of
// both directions gather into one output row at a time from whole input rows (the backward pads
// its scratch rows with zeros for that), so every inner loop runs over contiguous pixels and is
// vectorised by the compiler.
//
// The SLAM colour loss needs mean SSIM of the render against the observation, and its gradient
// with respect to the render only. In torch that is five filtered maps plus some forty small
// tensor operations forward and backward, whose per-call cost dominated the loss at 160x120.
// Here the forward filters the five maps x, y, x^2, y^2, xy of every channel (5C independent
// jobs for the threads) and sums the SSIM map row by row in double; the backward turns the
// scalar gradient into the gradients of mu_x, E[x^2] and E[xy] at each window position, filters
// those 3C maps back and combines them per pixel: dx = F'(g_mu) + 2 x F'(g_xx) + y F'(g_xy).
// Every sum has a fixed order, so nothing depends on the thread count.

#include <torch/extension.h>

#include <omp.h>

#include <algorithm>
#include <cstdint>
#include <vector>

namespace {

void check(const torch::Tensor& x, const torch::Tensor& k) {
  TORCH_CHECK(x.dim() == 3, "x must be [C, H, W]");
  TORCH_CHECK(k.dim() == 1 && k.size(0) > 0, "k must be [K]");
  TORCH_CHECK(x.scalar_type() == k.scalar_type(), "x and k must share the dtype");
  for (const auto* t : {&x, &k}) {
    TORCH_CHECK(t->is_contiguous() && t->device().is_cpu(), "inputs must be contiguous CPU");
  }
}

// x and y: the images SSIM compares, [C, H, W] each and at least as large as the filter.
void check_pair(const torch::Tensor& x, const torch::Tensor& y, const torch::Tensor& k) {
  check(x, k);
  check(y, k);
  TORCH_CHECK(x.sizes() == y.sizes(), "x and y must have the same size");
  TORCH_CHECK(x.size(1) >= k.size(0) && x.size(2) >= k.size(0),
              "the image must be at least as large as the filter");
}

template <typename S>
void forward_channel(const S* __restrict__ x, const S* __restrict__ k, int K, int H, int W,
                     S* __restrict__ row, S* __restrict__ out) {
  // row: [H, W2] scratch of the horizontal pass
  const int W2 = W - K + 1, H2 = H - K + 1;
  for (int i = 0; i < H; ++i) {
    const S* src = x + int64_t(i) * W;
    S* dst = row + int64_t(i) * W2;
    for (int j = 0; j < W2; ++j) dst[j] = k[0] * src[j];
    for (int b = 1; b < K; ++b) {
      const S kb = k[b];
      for (int j = 0; j < W2; ++j) dst[j] += kb * src[j + b];
    }
  }
  for (int i = 0; i < H2; ++i) {
    S* dst = out + int64_t(i) * W2;
    const S* src = row + int64_t(i) * W2;
    for (int j = 0; j < W2; ++j) dst[j] = k[0] * src[j];
    for (int a = 1; a < K; ++a) {
      const S ka = k[a];
      const S* s = src + int64_t(a) * W2;
      for (int j = 0; j < W2; ++j) dst[j] += ka * s[j];
    }
  }
}

template <typename S>
void backward_channel(const S* __restrict__ g, const S* __restrict__ k, int K, int H, int W,
                      S* __restrict__ row, S* __restrict__ gx) {
  // row: [H, P] gradient of the horizontal pass's output, each row with K - 1 zeros either side
  // (P = W2 + 2 (K - 1)), so that both passes gather into one output row at a time.
  const int W2 = W - K + 1, H2 = H - K + 1, P = W2 + 2 * (K - 1);
  for (int i = 0; i < H; ++i) {  // columns: row[i] = sum_a k[a] g[i - a], 0 <= i - a < H2
    S* dst = row + int64_t(i) * P;
    std::fill(dst, dst + K - 1, S(0));
    std::fill(dst + K - 1 + W2, dst + P, S(0));
    dst += K - 1;
    const int a0 = std::max(0, i - H2 + 1), a1 = std::min(K - 1, i);
    const S* src = g + int64_t(i - a0) * W2;
    for (int j = 0; j < W2; ++j) dst[j] = k[a0] * src[j];
    for (int a = a0 + 1; a <= a1; ++a) {
      const S ka = k[a];
      const S* s = g + int64_t(i - a) * W2;
      for (int j = 0; j < W2; ++j) dst[j] += ka * s[j];
    }
  }
  for (int i = 0; i < H; ++i) {  // rows: gx[i, j] = sum_b k[b] row[i, j - b]
    const S* src = row + int64_t(i) * P + (K - 1);
    S* dst = gx + int64_t(i) * W;
    for (int j = 0; j < W; ++j) dst[j] = k[0] * src[j];
    for (int b = 1; b < K; ++b) {
      const S kb = k[b];
      const S* s = src - b;
      for (int j = 0; j < W; ++j) dst[j] += kb * s[j];
    }
  }
}

// fn(j, scratch) for every job j < n (a channel, a row), the jobs split between threads, each
// thread with its own scratch buffer of `scratch` values.
template <typename S, typename F>
void each_job(int64_t n, int64_t scratch, const F& fn) {
  const int n_threads = int(std::min<int64_t>(std::max(1, at::get_num_threads()), n));
#pragma omp parallel num_threads(n_threads)
  {
    std::vector<S> buffer(static_cast<size_t>(scratch));
#pragma omp for schedule(static)
    for (int64_t j = 0; j < n; ++j) fn(j, buffer.data());
  }
}

// SSIM along one row of n window positions from the row's filtered maps mu_x, mu_y, E[x^2], E[y^2]
// and E[xy], with the operations of `ssim_maps` in its order (so that float32 rounds alike).
// Without Grad the SSIM goes to o_s; with Grad o_s, o_xx and o_xy get scale times dS/dmu_x,
// dS/dE[x^2] and dS/dE[xy]. Every row is its own restrict parameter (GCC does not vectorise the
// loop when it has to prove eight pointers apart at run time).
template <bool Grad, typename S>
void ssim_row(const S* __restrict__ f_mx, const S* __restrict__ f_my, const S* __restrict__ f_xx,
              const S* __restrict__ f_yy, const S* __restrict__ f_xy, int64_t n, S c1, S c2,
              S scale, S* __restrict__ o_s, S* __restrict__ o_xx, S* __restrict__ o_xy) {
  for (int64_t q = 0; q < n; ++q) {
    const S mx = f_mx[q], my = f_my[q];
    const S sxx = f_xx[q] - mx * mx, syy = f_yy[q] - my * my, sxy = f_xy[q] - mx * my;
    const S b2 = sxx + syy + c2, b1 = mx * mx + my * my + c1;
    const S cs = (S(2) * sxy + c2) / b2;
    const S lum = (S(2) * mx * my + c1) / b1;
    if constexpr (Grad) {
      // lum = A1 / B1 and cs = A2 / B2 with A1 = 2 mx my + c1, B1 = mx^2 + my^2 + c1,
      // A2 = 2 (E[xy] - mx my) + c2, B2 = E[x^2] - mx^2 + E[y^2] - my^2 + c2
      const S d_lum = (S(2) * my - lum * S(2) * mx) / b1;
      const S d_cs = (S(2) * cs * mx - S(2) * my) / b2;
      o_s[q] = scale * (cs * d_lum + lum * d_cs);
      o_xx[q] = scale * (-(lum * cs) / b2);
      o_xy[q] = scale * (S(2) * lum / b2);
    } else {
      o_s[q] = lum * cs;
    }
  }
}

}  // namespace


torch::Tensor blur_forward(torch::Tensor x, torch::Tensor k) {
  check(x, k);
  const int64_t C = x.size(0), H = x.size(1), W = x.size(2), K = k.size(0);
  TORCH_CHECK(H >= K && W >= K, "the image must be at least as large as the filter");
  const int64_t H2 = H - K + 1, W2 = W - K + 1;
  auto out = torch::empty({C, H2, W2}, x.options());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "blur_forward", [&] {
    const scalar_t* xs = x.data_ptr<scalar_t>();
    const scalar_t* ks = k.data_ptr<scalar_t>();
    scalar_t* os = out.data_ptr<scalar_t>();
    each_job<scalar_t>(C, H * W2, [&](int64_t c, scalar_t* row) {
      forward_channel<scalar_t>(xs + c * H * W, ks, int(K), int(H), int(W), row, os + c * H2 * W2);
    });
  });
  return out;
}

torch::Tensor blur_backward(torch::Tensor grad, torch::Tensor k, int64_t H, int64_t W) {
  TORCH_CHECK(grad.dim() == 3, "grad must be [C, H - K + 1, W - K + 1]");
  check(grad, k);
  const int64_t C = grad.size(0), K = k.size(0), H2 = H - K + 1, W2 = W - K + 1;
  TORCH_CHECK(grad.size(1) == H2 && grad.size(2) == W2, "grad has the wrong size");
  auto gx = torch::empty({C, H, W}, grad.options());
  AT_DISPATCH_FLOATING_TYPES(grad.scalar_type(), "blur_backward", [&] {
    const scalar_t* gs = grad.data_ptr<scalar_t>();
    const scalar_t* ks = k.data_ptr<scalar_t>();
    scalar_t* xs = gx.data_ptr<scalar_t>();
    each_job<scalar_t>(C, H * (W2 + 2 * (K - 1)), [&](int64_t c, scalar_t* row) {
      backward_channel<scalar_t>(gs + c * H2 * W2, ks, int(K), int(H), int(W), row, xs + c * H * W);
    });
  });
  return gx;
}

std::vector<torch::Tensor> ssim_forward(torch::Tensor x, torch::Tensor y, torch::Tensor k,
                                        double c1, double c2) {
  check_pair(x, y, k);
  const int64_t C = x.size(0), H = x.size(1), W = x.size(2), K = k.size(0);
  const int64_t H2 = H - K + 1, W2 = W - K + 1;
  auto filtered = torch::empty({5, C, H2, W2}, x.options());  // mu_x, mu_y, E[x^2], E[y^2], E[xy]
  std::vector<double> row_sums(static_cast<size_t>(C * H2));
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "ssim_forward", [&] {
    const scalar_t* xs = x.data_ptr<scalar_t>();
    const scalar_t* ys = y.data_ptr<scalar_t>();
    const scalar_t* ks = k.data_ptr<scalar_t>();
    scalar_t* fs = filtered.data_ptr<scalar_t>();
    const int64_t plane = H2 * W2;
    each_job<scalar_t>(5 * C, H * W + H * W2, [&](int64_t j, scalar_t* scratch) {
      const int64_t m = j / C, c = j % C;
      const scalar_t* a = xs + c * H * W;
      const scalar_t* b = ys + c * H * W;
      const scalar_t* src = m == 1 ? b : a;
      if (m >= 2) {  // the product map into the scratch's first H * W values
        const scalar_t* u = m == 3 ? b : a;
        const scalar_t* v = m == 2 ? a : b;
        for (int64_t i = 0; i < H * W; ++i) scratch[i] = u[i] * v[i];
        src = scratch;
      }
      forward_channel<scalar_t>(src, ks, int(K), int(H), int(W), scratch + H * W, fs + j * plane);
    });
    const scalar_t s1 = scalar_t(c1), s2 = scalar_t(c2);
    const int64_t cp = C * plane;
    each_job<scalar_t>(C * H2, W2, [&](int64_t r, scalar_t* row) {
      const int64_t at = (r / H2) * plane + (r % H2) * W2;
      const scalar_t* f = fs + at;
      ssim_row<false>(f, f + cp, f + 2 * cp, f + 3 * cp, f + 4 * cp, W2, s1, s2, scalar_t(1), row,
                      static_cast<scalar_t*>(nullptr), static_cast<scalar_t*>(nullptr));
      double sum = 0;
      for (int64_t q = 0; q < W2; ++q) sum += row[q];
      row_sums[static_cast<size_t>(r)] = sum;
    });
  });
  double total = 0;
  for (double v : row_sums) total += v;
  auto mean = torch::full({}, total / double(C * H2 * W2), x.options());
  return {mean, filtered};
}

torch::Tensor ssim_backward(torch::Tensor x, torch::Tensor y, torch::Tensor k,
                            torch::Tensor filtered, torch::Tensor grad, double c1, double c2) {
  check_pair(x, y, k);
  const int64_t C = x.size(0), H = x.size(1), W = x.size(2), K = k.size(0);
  const int64_t H2 = H - K + 1, W2 = W - K + 1, plane = H2 * W2;
  TORCH_CHECK(filtered.sizes() == at::IntArrayRef({5, C, H2, W2}),
              "filtered must be ssim_forward's [5, C, H2, W2]");
  check(filtered.flatten(0, 1), k);
  const double g = grad.item<double>() / double(C * plane);
  auto d_filtered = torch::empty({3, C, H2, W2}, x.options());  // d mu_x, d E[x^2], d E[xy]
  auto d_maps = torch::empty({3, C, H, W}, x.options());
  auto dx = torch::empty_like(x);
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "ssim_backward", [&] {
    const scalar_t* xs = x.data_ptr<scalar_t>();
    const scalar_t* ys = y.data_ptr<scalar_t>();
    const scalar_t* ks = k.data_ptr<scalar_t>();
    const scalar_t* fs = filtered.data_ptr<scalar_t>();
    scalar_t* ds = d_filtered.data_ptr<scalar_t>();
    scalar_t* ms = d_maps.data_ptr<scalar_t>();
    scalar_t* out = dx.data_ptr<scalar_t>();
    const scalar_t s1 = scalar_t(c1), s2 = scalar_t(c2), gs = scalar_t(g);
    const int64_t cp = C * plane;
    each_job<scalar_t>(C * H2, 0, [&](int64_t r, scalar_t*) {
      const int64_t at = (r / H2) * plane + (r % H2) * W2;
      const scalar_t* f = fs + at;
      scalar_t* d = ds + at;
      ssim_row<true>(f, f + cp, f + 2 * cp, f + 3 * cp, f + 4 * cp, W2, s1, s2, gs, d, d + cp,
                     d + 2 * cp);
    });
    each_job<scalar_t>(3 * C, H * (W2 + 2 * (K - 1)), [&](int64_t j, scalar_t* row) {
      backward_channel<scalar_t>(ds + j * plane, ks, int(K), int(H), int(W), row, ms + j * H * W);
    });
    const int64_t cm = C * H * W;
    each_job<scalar_t>(C * H, 0, [&](int64_t r, scalar_t*) {
      const scalar_t* __restrict__ g_mu = ms + r * W;
      const scalar_t* __restrict__ g_xx = g_mu + cm;
      const scalar_t* __restrict__ g_xy = g_mu + 2 * cm;
      const scalar_t* __restrict__ xr = xs + r * W;
      const scalar_t* __restrict__ yr = ys + r * W;
      scalar_t* __restrict__ o = out + r * W;
      for (int64_t q = 0; q < W; ++q) {
        o[q] = g_mu[q] + scalar_t(2) * xr[q] * g_xx[q] + yr[q] * g_xy[q];
      }
    });
  });
  return dx;
}
