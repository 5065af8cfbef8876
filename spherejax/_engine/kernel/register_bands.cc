// The registration of spherejax.band_resampling (`registered_frames`) as an XLA FFI handler, the
// custom call "spherejax_register_bands" that spherejax._engine.fused_registration calls on CPU:
// each band's flat-fielded response (Eq. 10, in the band's own geometry) sampled bilinearly through
// the band's 2 x 3 map into the reference band's geometry, the registered pixel's quality bits,
// and u' = v' s' (or -s' where flagged).
//
// Why this exists: XLA's CPU gather takes about 1 ns an element and the registration reads four
// taps of three arrays for every value: 250 ms a megapixel of 16 bands on 2 Zen 4 cores, ten
// times the correction it precedes; this loop reads each tap once, where it lies (benchmarks/README.md).
//
// It computes what the jax.numpy definition computes, in float32, value by value:
//   xs = m00 x + m01 y + m02, ys = m10 x + m11 y + m12          the band's map (row-major B x 6)
//   bit 32 unless -1e-3 <= xs <= W - 1 + 1e-3 and the same for ys (not covered)
//   xs, ys clamped into the frame; x0 = min(floor(xs), W - 2), fx = xs - x0 (likewise y)
//   the four taps (y0|y1, x0|x1), weights (1 - fy)(1 - fx), (1 - fy) fx, fy (1 - fx), fy fx; a tap
//   of weight > 0 on a native value that is not finite sets bit 2, at or above the saturation
//   level bit 1, without a flat field (inverse signal not > 0) bit 4; else it adds
//   weight * (raw - dark) * inverse_signal
//   u' = (bits == 0 ? sum : -1) * registered_signal              per pixel over its bands' bits
// Layout: raw (N, H, W, B) uint16 or float32; dark, inverse_signal (1 / (white - dark) where that
// is finite and > 0, else 0), registered_signal (H, W, B) float32; maps (B, 2, 3) float32; outputs
// frames (N, H, W, B) float32 and bits (N, H, W) uint8. Rows are shared out to XLA's pool.

#include <algorithm>
#include <atomic>
#include <cmath>
#include <condition_variable>
#include <cstdint>
#include <memory>
#include <mutex>
#include <type_traits>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace spherejax_register {
namespace {

constexpr uint8_t kSaturated = 1, kNonfinite = 2, kWhiteNotAboveDark = 4, kNotCovered = 32;
constexpr float kCoverageTolerance = 1e-3f;  // band_resampling.COVERAGE_TOLERANCE_PX
constexpr int64_t kMaxBands = 256;           // spherejax.calibration.MAX_BANDS
constexpr int64_t kRowsPerChunk = 16;

struct Registration {
  const void* raw = nullptr;
  bool u16 = true;
  int64_t images = 0, height = 0, width = 0, bands = 0;
  const float *dark = nullptr, *inverse_signal = nullptr, *registered_signal = nullptr, *maps = nullptr;
  float saturation = NAN;  // NaN: no check (value >= NaN is never true)
  float* frames = nullptr;
  uint8_t* bits = nullptr;
};

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#define SPHEREJAX_REGISTER_CLONES __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define SPHEREJAX_REGISTER_CLONES
#endif

// One registered pixel (y, x) of one image, exactly as the header says: its bands' values and its
// bits. What the fast path below falls back to wherever a pixel came out NaN (flagged, or a
// zero-weight tap on a flagged native value, which this leaves out).
template <typename Raw>
void register_pixel(const Registration& r, const Raw* raw, int64_t y, int64_t x, float* out, uint8_t* bits_out) {
  constexpr bool kIntegerRaw = std::is_integral<Raw>::value;  // counts are always finite
  const int64_t H = r.height, W = r.width, B = r.bands;
  const float last_x = static_cast<float>(W - 1), last_y = static_cast<float>(H - 1);
  const int64_t top_x = std::max<int64_t>(W - 2, 0), top_y = std::max<int64_t>(H - 2, 0);
  const float fy_row = static_cast<float>(y), fx_col = static_cast<float>(x);
  float values[kMaxBands];
  uint8_t bits = 0;
  for (int64_t b = 0; b < B; ++b) {
    const float* m = r.maps + 6 * b;
    float xs = m[0] * fx_col + m[1] * fy_row + m[2];
    float ys = m[3] * fx_col + m[4] * fy_row + m[5];
    if (!(xs >= -kCoverageTolerance && xs <= last_x + kCoverageTolerance && ys >= -kCoverageTolerance &&
          ys <= last_y + kCoverageTolerance)) {
      bits |= kNotCovered;
    }
    xs = std::min(std::max(xs, 0.0f), last_x);
    ys = std::min(std::max(ys, 0.0f), last_y);
    if (!(xs == xs)) xs = 0.0f;  // a NaN map: flagged above, sampled anywhere valid
    if (!(ys == ys)) ys = 0.0f;
    // xs, ys >= 0 here: truncation is floor, without the libm call std::floor becomes where the
    // baseline x86-64 has no rounding instruction.
    const int64_t x0 = std::min<int64_t>(static_cast<int64_t>(xs), top_x);
    const int64_t y0 = std::min<int64_t>(static_cast<int64_t>(ys), top_y);
    const float fx = xs - static_cast<float>(x0), fy = ys - static_cast<float>(y0);
    const int64_t x1 = std::min(x0 + 1, W - 1), y1 = std::min(y0 + 1, H - 1);
    const int64_t taps[4] = {(y0 * W + x0) * B + b, (y0 * W + x1) * B + b, (y1 * W + x0) * B + b,
                             (y1 * W + x1) * B + b};
    const float weights[4] = {(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx};
    float sum = 0.0f;
    for (int k = 0; k < 4; ++k) {
      if (!(weights[k] > 0)) continue;
      const float value = static_cast<float>(raw[taps[k]]);
      const float inverse = r.inverse_signal[taps[k]];
      if (!kIntegerRaw && !std::isfinite(value)) {
        bits |= kNonfinite;
      } else if (value >= r.saturation) {
        bits |= kSaturated;
      }
      if (!(inverse > 0)) bits |= kWhiteNotAboveDark;
      // A flagged tap's value does not matter: its pixel is written as -s below.
      sum += weights[k] * ((value - r.dark[taps[k]]) * inverse);
    }
    values[b] = sum;
  }
  const float* s = r.registered_signal + (y * W + x) * B;
  for (int64_t b = 0; b < B; ++b) out[b] = (bits == 0 ? values[b] : -1.0f) * s[b];
  *bits_out = bits;
}

// The fast path's loops are compiled without trapping math (floating-point exceptions are never
// unmasked here): otherwise GCC keeps a float-to-int conversion and the selects as branches and
// does not vectorise them (gathers with AVX2 and AVX-512).
#pragma GCC push_options
#pragma GCC optimize("no-trapping-math")

// The fast path's pass 1: native rows [row0, row1) of one image as planes of flat-fielded
// responses, planes[b][(y - row0) W + x], NaN where the native value is flagged (not finite,
// saturated, no flat field).
template <typename Raw>
SPHEREJAX_REGISTER_CLONES void native_planes(const Registration& r, const Raw* __restrict raw, int64_t row0,
                                             int64_t row1, float* __restrict planes) {
  const int64_t W = r.width, B = r.bands, plane = (row1 - row0) * W;
  const float saturation = r.saturation;
  for (int64_t y = row0; y < row1; ++y) {
    for (int64_t b = 0; b < B; ++b) {
      const int64_t i = y * W * B + b;
      float* __restrict to = planes + b * plane + (y - row0) * W;
      for (int64_t x = 0; x < W; ++x) {
        const float value = static_cast<float>(raw[i + x * B]);
        const float inverse = r.inverse_signal[i + x * B];
        // Finite and unsaturated, with a flat field (bitwise &: no branches).
        const bool good = !(value >= saturation) & (inverse > 0) & (value - value == 0);
        const float v = (value - r.dark[i + x * B]) * inverse;
        to[x] = good ? v : NAN;
      }
    }
  }
}

// The fast path's pass 2: one registered row y of band b from its native plane (rows [row0,
// row1) of the image), NaN where the pixel lies outside the band's frame or a tap is NaN.
SPHEREJAX_REGISTER_CLONES void sample_row(const Registration& r, const float* __restrict plane, int64_t row0,
                                          int64_t row1, int64_t y, int64_t b, float* __restrict out) {
  const int32_t W = static_cast<int32_t>(r.width), H = static_cast<int32_t>(r.height);
  const float last_x = static_cast<float>(W - 1), last_y = static_cast<float>(H - 1);
  const int32_t top_x = std::max(W - 2, 0), top_y = std::max(H - 2, 0);
  const int32_t first = static_cast<int32_t>(row0), last = static_cast<int32_t>(row1) - 1;
  const float* m = r.maps + 6 * b;
  const float m0 = m[0], m3 = m[3], row_x = m[1] * static_cast<float>(y), row_y = m[4] * static_cast<float>(y);
  const float m2 = m[2], m5 = m[5];
  // Branch-free (selects, bitwise &), so that the compiler vectorises it with gathers.
  for (int32_t x = 0; x < W; ++x) {
    const float fx_col = static_cast<float>(x);
    float xs = m0 * fx_col + row_x + m2;
    float ys = m3 * fx_col + row_y + m5;
    const bool covered = (xs >= -kCoverageTolerance) & (xs <= last_x + kCoverageTolerance) &
                         (ys >= -kCoverageTolerance) & (ys <= last_y + kCoverageTolerance);
    xs = xs > 0.0f ? xs : 0.0f;
    xs = xs < last_x ? xs : last_x;
    ys = ys > 0.0f ? ys : 0.0f;
    ys = ys < last_y ? ys : last_y;
    int32_t x0 = static_cast<int32_t>(xs);
    x0 = x0 < top_x ? x0 : top_x;
    int32_t y0 = static_cast<int32_t>(ys);
    y0 = y0 < top_y ? y0 : top_y;
    const float fx = xs - static_cast<float>(x0), fy = ys - static_cast<float>(y0);
    const int32_t x1 = x0 + 1 < W ? x0 + 1 : W - 1;
    int32_t y1 = y0 + 1 < H ? y0 + 1 : H - 1;
    // Rows within the planes (the halo covers every row a map reaches; clamped all the same).
    int32_t r0 = y0 > first ? y0 : first;
    r0 = r0 < last ? r0 : last;
    int32_t r1 = y1 > first ? y1 : first;
    r1 = r1 < last ? r1 : last;
    const int32_t a = (r0 - first) * W, c = (r1 - first) * W;
    const float sum = (1 - fy) * (1 - fx) * plane[a + x0] + (1 - fy) * fx * plane[a + x1] +
                      fy * (1 - fx) * plane[c + x0] + fy * fx * plane[c + x1];
    out[x] = covered ? sum : NAN;
  }
}

#pragma GCC pop_options

// Output rows [first, last) of the images (row index = image * H + y, within one image), by the
// fast path: the native planes the rows need, each band's row sampled, then written out
// interleaved times s'; a pixel with any NaN band is done again exactly (register_pixel).
template <typename Raw>
void register_rows(const Registration& r, int64_t first, int64_t last, int64_t halo, std::vector<float>& work) {
  const int64_t H = r.height, W = r.width, B = r.bands;
  const int64_t image = first / H, y_first = first % H, y_last = (last - 1) % H + 1;
  const Raw* raw = static_cast<const Raw*>(r.raw) + image * H * W * B;
  const int64_t row0 = std::max<int64_t>(y_first - halo, 0), row1 = std::min<int64_t>(y_last + halo, H);
  const int64_t plane = (row1 - row0) * W;
  work.resize(size_t(B * plane + B * W));
  float* planes = work.data();
  float* rows = planes + B * plane;
  native_planes<Raw>(r, raw, row0, row1, planes);
  for (int64_t y = y_first; y < y_last; ++y) {
    for (int64_t b = 0; b < B; ++b) sample_row(r, planes + b * plane, row0, row1, y, b, rows + b * W);
    float* out = r.frames + ((image * H + y) * W) * B;
    uint8_t* bits = r.bits + (image * H + y) * W;
    const float* s = r.registered_signal + y * W * B;
    for (int64_t x = 0; x < W; ++x) {
      bool finite = true;
      for (int64_t b = 0; b < B; ++b) {
        const float value = rows[b * W + x];
        finite &= value - value == 0;
        out[x * B + b] = value * s[x * B + b];
      }
      bits[x] = 0;
      if (!finite) register_pixel<Raw>(r, raw, y, x, out + x * B, bits + x);
    }
  }
}

// Chunks of rows handed out by an atomic counter to the calling thread and XLA's pool (as the
// fused correction's, call.h); shared-owned, so that a task the pool starts late finds no chunk
// left and only drops its reference.
struct Shared {
  Registration problem;
  int64_t chunks = 0;
  std::atomic<int64_t> next{0}, finished{0};
  std::mutex mutex;
  std::condition_variable all_done;

  int64_t halo = 1;             // native rows beyond a chunk's that its maps reach
  int64_t chunks_per_image = 1;

  void work() {
    std::vector<float> buffer;  // this thread's planes, reused chunk after chunk
    const int64_t H = problem.height;
    for (int64_t chunk; (chunk = next.fetch_add(1)) < chunks;) {
      // Chunks never straddle two images.
      const int64_t image = chunk / chunks_per_image, k = chunk % chunks_per_image;
      const int64_t first = image * H + k * kRowsPerChunk, last = image * H + std::min(H, (k + 1) * kRowsPerChunk);
      if (problem.u16) {
        register_rows<uint16_t>(problem, first, last, halo, buffer);
      } else {
        register_rows<float>(problem, first, last, halo, buffer);
      }
      if (finished.fetch_add(1) + 1 == chunks) {
        std::lock_guard<std::mutex> lock(mutex);
        all_done.notify_all();
      }
    }
  }
};

ffi::Error Register(ffi::ThreadPool pool, ffi::AnyBuffer raw, ffi::Buffer<ffi::F32> dark,
                    ffi::Buffer<ffi::F32> inverse_signal, ffi::Buffer<ffi::F32> registered_signal,
                    ffi::Buffer<ffi::F32> maps, float saturation, ffi::ResultBuffer<ffi::F32> frames,
                    ffi::ResultBuffer<ffi::U8> bits) {
  const auto dims = raw.dimensions();
  if (dims.size() != 4) return ffi::Error::InvalidArgument("raw: expected (N, H, W, B)");
  const bool u16 = raw.element_type() == ffi::U16;
  if (!u16 && raw.element_type() != ffi::F32) return ffi::Error::InvalidArgument("raw: expected uint16 or float32");
  auto shared = std::make_shared<Shared>();
  Registration& r = shared->problem;
  r.images = dims[0], r.height = dims[1], r.width = dims[2], r.bands = dims[3];
  const size_t frame = size_t(r.height * r.width * r.bands);
  if (r.bands < 1 || r.bands > kMaxBands) return ffi::Error::InvalidArgument("bands: expected 1..256");
  if (dark.element_count() != frame || inverse_signal.element_count() != frame ||
      registered_signal.element_count() != frame || maps.element_count() != size_t(r.bands * 6)) {
    return ffi::Error::InvalidArgument("inputs: shapes do not match raw (N, H, W, B)");
  }
  r.raw = raw.untyped_data();
  r.u16 = u16;
  r.dark = dark.typed_data();
  r.inverse_signal = inverse_signal.typed_data();
  r.registered_signal = registered_signal.typed_data();
  r.maps = maps.typed_data();
  r.saturation = saturation;
  r.frames = frames->typed_data();
  r.bits = bits->typed_data();
  shared->chunks_per_image = (r.height + kRowsPerChunk - 1) / kRowsPerChunk;
  shared->chunks = r.images * shared->chunks_per_image;
  // The rows a map reaches beyond its own: the largest vertical displacement over the frame's
  // corners, rounded up, and the bilinear kernel's one (band_resampling.halo_px).
  float reach = 0.0f;
  for (int64_t b = 0; b < r.bands; ++b) {
    const float* m = r.maps + 6 * b;
    for (float cx : {0.0f, float(r.width - 1)}) {
      for (float cy : {0.0f, float(r.height - 1)}) {
        const float dy = m[3] * cx + m[4] * cy + m[5] - cy;
        reach = std::max(reach, std::fabs(dy));
      }
    }
  }
  if (!(reach <= float(r.height))) reach = float(r.height);  // NaN maps: every row
  shared->halo = static_cast<int64_t>(std::ceil(reach)) + 2;
  const int64_t helpers = std::min<int64_t>(pool.num_threads(), shared->chunks - 1);
  for (int64_t t = 0; t < helpers; ++t) pool.Schedule([shared] { shared->work(); });
  shared->work();
  std::unique_lock<std::mutex> lock(shared->mutex);
  shared->all_done.wait(lock, [&] { return shared->finished.load() == shared->chunks; });
  return ffi::Error::Success();
}

}  // namespace
}  // namespace spherejax_register

XLA_FFI_DEFINE_HANDLER_SYMBOL(SpherejaxRegisterBands, spherejax_register::Register,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::AnyBuffer>()           // raw
                                  .Arg<ffi::Buffer<ffi::F32>>()    // dark
                                  .Arg<ffi::Buffer<ffi::F32>>()    // inverse signal
                                  .Arg<ffi::Buffer<ffi::F32>>()    // registered signal
                                  .Arg<ffi::Buffer<ffi::F32>>()    // maps
                                  .Attr<float>("saturation")
                                  .Ret<ffi::Buffer<ffi::F32>>()    // frames
                                  .Ret<ffi::Buffer<ffi::U8>>());   // bits
