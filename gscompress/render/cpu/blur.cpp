// The separable 'valid' Gaussian filter of SSIM (`gscompress.metrics.blur`) and its backward.
//
// x [C, H, W] -> [C, H - K + 1, W - K + 1]: each channel filtered along its rows (W) with the
// K taps k, then along its columns (H), as the two grouped convolutions of the torch version do.
// The SLAM colour loss filters five maps of three channels per mapping iteration; at 160x120 the
// two convolutions and their backward took about a fifth of a mapping step in torch, for some
// 10 MFLOP, most of it per-call overhead of the grouped convolution.
//
// The backward is the transposed filter, columns first, then rows. Both passes of both directions
// gather into one output row at a time from whole input rows (the backward pads its scratch rows
// with zeros for that), so every inner loop runs over contiguous pixels and is vectorised by the
// compiler; channels are independent and are split between threads.

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

// fn(c, scratch) for every channel c < C, the channels split between threads, each thread with
// its own scratch buffer of `scratch` values.
template <typename S, typename F>
void each_channel(int64_t C, int64_t scratch, const F& fn) {
  const int n_threads = int(std::min<int64_t>(std::max(1, at::get_num_threads()), C));
#pragma omp parallel num_threads(n_threads)
  {
    std::vector<S> buffer(static_cast<size_t>(scratch));
#pragma omp for schedule(static)
    for (int64_t c = 0; c < C; ++c) fn(c, buffer.data());
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
    each_channel<scalar_t>(C, H * W2, [&](int64_t c, scalar_t* row) {
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
    each_channel<scalar_t>(C, H * (W2 + 2 * (K - 1)), [&](int64_t c, scalar_t* row) {
      backward_channel<scalar_t>(gs + c * H2 * W2, ks, int(K), int(H), int(W), row, xs + c * H * W);
    });
  });
  return gx;
}
