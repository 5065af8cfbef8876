// The bands brought into register (spherejax.band_resampling) as the compiled code computes them:
// the native frames a registration reads, one registered pixel exactly as the definition does
// (register_pixel), and the fast path's two passes over rows (registered_rows.cc): the native
// flat-fielded responses of some rows, and registered rows sampled from them.
//
// Two callers: register_bands.cc (the custom call that writes registered frames, u' = v' s') and
// call.cc (the fused correction of a calibration with band maps, which registers each chunk's rows
// into a buffer of its own and corrects them from there, so that no registered frame is written
// or read back).
//
// The equations, value by value, in float32:
//   xs = m00 x + m01 y + m02, ys = m10 x + m11 y + m12          the band's map (row-major B x 6)
//   bit 32 unless -1e-3 <= xs <= W - 1 + 1e-3 and the same for ys (not covered)
//   xs, ys clamped into the frame; x0 = min(floor(xs), W - 2), fx = xs - x0 (likewise y)
//   the four taps (y0|y1, x0|x1), weights (1 - fy)(1 - fx), (1 - fy) fx, fy (1 - fx), fy fx; a tap
//   of weight > 0 on a native value that is not finite sets bit 2, at or above the saturation
//   level bit 1, without a flat field (inverse signal not > 0) bit 4; else it adds
//   weight * (raw - dark) * inverse_signal                       = v', the registered response

#ifndef SPHEREJAX_BAND_TAPS_H_
#define SPHEREJAX_BAND_TAPS_H_

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <type_traits>

namespace spherejax_bands {

constexpr uint8_t kSaturated = 1, kNonfinite = 2, kWhiteNotAboveDark = 4, kNotCovered = 32;
constexpr float kCoverageTolerance = 1e-3f;  // band_resampling.COVERAGE_TOLERANCE_PX
constexpr int64_t kMaxBands = 256;           // spherejax.calibration.MAX_BANDS

// The native frames of one call: raw (N, H, W, B) uint16 or float32; dark and inverse_signal
// (1 / (white - dark) where that is finite and > 0, else 0) (H, W, B) float32; maps (B, 2, 3)
// float32, each from the reference band's pixel coordinates to the band's (x = column, y = row).
struct NativeFrames {
  const void* raw = nullptr;
  bool u16 = true;
  int64_t height = 0, width = 0, bands = 0;
  const float *dark = nullptr, *inverse_signal = nullptr, *maps = nullptr;
  float saturation = NAN;  // NaN: no check (value >= NaN is never true)
  // Whether the sampler may use AVX-512 (AVX2): set by the caller where the CPU runs it
  // (spherejax_fused::variant_supported), and not where the caller was asked for narrower code (the
  // fused kernel's forced variants, SPHEREJAX_FUSED), so that what is measured as AVX2 runs no
  // AVX-512 instruction.
  bool avx512 = false, avx2 = false;
};

// The native rows beyond its own that a registered row reads: the largest vertical displacement
// of any band at the frame's corners, rounded up, plus the bilinear kernel's one and a spare
// (band_resampling.halo_px); every row for maps that are not finite.
inline int64_t halo_rows(const NativeFrames& f) {
  float reach = 0.0f;
  for (int64_t b = 0; b < f.bands; ++b) {
    const float* m = f.maps + 6 * b;
    for (float cx : {0.0f, float(f.width - 1)}) {
      for (float cy : {0.0f, float(f.height - 1)}) {
        const float dy = m[3] * cx + m[4] * cy + m[5] - cy;
        reach = std::max(reach, std::fabs(dy));
      }
    }
  }
  if (!(reach <= float(f.height))) reach = float(f.height);
  return static_cast<int64_t>(std::ceil(reach)) + 2;
}

// One registered pixel (y, x) of the image whose raw starts at `raw`, exactly as the header says:
// its bands' v' into values (B) and its bits returned. What the fast path falls back to wherever
// a pixel came out NaN (flagged, or a zero-weight tap on a flagged native value, which this leaves
// out).
template <typename Raw>
uint8_t register_pixel(const NativeFrames& f, const Raw* raw, int64_t y, int64_t x, float* values) {
  constexpr bool kIntegerRaw = std::is_integral<Raw>::value;  // counts are always finite
  const int64_t H = f.height, W = f.width, B = f.bands;
  const float last_x = static_cast<float>(W - 1), last_y = static_cast<float>(H - 1);
  const int64_t top_x = std::max<int64_t>(W - 2, 0), top_y = std::max<int64_t>(H - 2, 0);
  const float fy_row = static_cast<float>(y), fx_col = static_cast<float>(x);
  uint8_t bits = 0;
  for (int64_t b = 0; b < B; ++b) {
    const float* m = f.maps + 6 * b;
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
      const float inverse = f.inverse_signal[taps[k]];
      if (!kIntegerRaw && !std::isfinite(value)) {
        bits |= kNonfinite;
      } else if (value >= f.saturation) {
        bits |= kSaturated;
      }
      if (!(inverse > 0)) bits |= kWhiteNotAboveDark;
      // A flagged tap's value does not matter: the caller replaces a flagged pixel's values.
      sum += weights[k] * ((value - f.dark[taps[k]]) * inverse);
    }
    values[b] = sum;
  }
  return bits;
}

// The fast path (registered_rows.cc), for one image n of f:
//
// native_responses: native rows [row0, row1) as flat-fielded responses, interleaved as the frames
// are, out[((y - row0) W + x) B + b] = (raw - dark) * inverse_signal, NaN where the native value is
// flagged (not finite, saturated, no flat field).
void native_responses(const NativeFrames& f, int64_t image, int64_t row0, int64_t row1, float* out);

// registered_row: registered row y from the native responses of rows [row0, row1) (which must hold
// every row the maps reach from y: halo_rows), out[x B + b] = v' and bits[x] for x in [0, W). A
// pixel that comes out NaN is done again exactly (register_pixel); a flagged pixel's values are
// `placeholder` in every band.
void registered_row(const NativeFrames& f, int64_t image, const float* native, int64_t row0, int64_t row1, int64_t y,
                    float placeholder, float* out, uint8_t* bits);

}  // namespace spherejax_bands

#endif  // SPHEREJAX_BAND_TAPS_H_
