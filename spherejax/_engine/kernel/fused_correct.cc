// The per-pixel path of spherejax.correct as one fused CPU kernel, called from XLA (FFI).
//
// Why this exists. XLA on CPU does not fuse a matrix product with elementwise work, so the
// plain jitted path (spherejax/pipeline.py, `_correct_pixels_plain`) writes the Stage II cube
// and the white signal to memory and reads them back for the Wiener and XYZ products: about
// 500 MB a megapixel against the 297 bytes a pixel the path must move, and XLA's elementwise
// loops reach only part of the copy bandwidth (benchmarks/README.md, "Where the time of
// `correct` goes"). This kernel reads each pixel once and writes its outputs once.
//
// It computes exactly the equations of the plain path, in float32, pixel by pixel:
//   quality  bits: 1 saturated (finite raw >= saturation in some band), 2 raw not finite,
//            4 white - dark not finite and > 0 in some band, 8 the image's p not finite,
//            16 v below -kBelowDarkLimit in some band whose raw is finite and white - dark
//            finite and > 0
//   v        = (raw - dark) / (white - dark)                         (Eq. 10)
//   v_tilde  = (c1 p + c2) v + c3 p + c4                              (Eq. 17 and 23)
//   [reflectance | XYZ] = v_tilde @ projection + bias                 (the affine Wiener estimate
//            W v_tilde + r0, 16 -> 31, and the folded (B, 3) XYZ matrix with its offset r0 @
//            weights: one (B, 34) product whose accumulators start at the (34,) bias)
//   Lab      = CIE 1976 from XYZ / white_xyz                          (CIE 15:2004)
// and NaN in reflectance and Lab wherever quality != 0. The tests compare it with the plain
// path on every branch (tests/test_fused.py).
//
// Each pixel goes through the same code wherever it lies (the last block of a range is padded,
// never handled by a scalar tail), so a strip of an image gives the same bits as the whole image.
//
// Layout: raw (N, P, B) uint16 or float32, dark and white (P, B), p (N, B), coeffs (B, 4),
// projection (B, 34), bias (34,), white_xyz (3,); outputs reflectance (N, P, 31), Lab (N, P, 3), quality
// (N, P) uint8. The work is split into chunks of pixels run on XLA's intra-op thread pool.

#include <Python.h>

#if defined(__x86_64__)
#include <immintrin.h>
#endif

#include <algorithm>
#include <atomic>
#include <cmath>
#include <condition_variable>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <mutex>
#include <new>
#include <thread>
#include <type_traits>
#include <vector>

#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

constexpr int64_t kReflectance = 31;            // 400..700 nm step 10
constexpr int64_t kOutputs = kReflectance + 3;  // reflectance then X, Y, Z
constexpr int64_t kLanes = 16;                  // floats in one 512-bit vector
constexpr int64_t kPadded = 48;                 // kOutputs rounded up to whole vectors
constexpr int64_t kMaxBands = 64;
constexpr int64_t kBlock = 32;                  // pixels whose XYZ are turned into Lab together
constexpr int64_t kChunk = 8192;                // pixels per thread-pool task
constexpr float kLabEpsilon = 216.0f / 24389.0f;
constexpr float kLabKappa = 24389.0f / 27.0f;
// pipeline.BELOW_DARK_LIMIT (its comment says why 2 %): the same number, or the bits differ.
constexpr float kBelowDarkLimit = 0.02f;

// GCC/Clang vector extension: 16 floats. Compiled for each target of `target_clones` below, it
// is one zmm register with AVX-512, two ymm with AVX2, four xmm otherwise.
typedef float Vec __attribute__((vector_size(kLanes * sizeof(float)), aligned(64)));

#if defined(__x86_64__) && defined(__GNUC__)
#define SPHEREJAX_CLONES __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define SPHEREJAX_CLONES
#endif
#define SPHEREJAX_INLINE inline __attribute__((always_inline))

struct Problem {
  const void* raw;
  bool raw_is_u16;
  const float* dark;
  const float* white;
  int64_t images, pixels, bands;
  float saturation;  // NaN: no saturation check
  bool portable;     // skip the AVX-512 code even where the CPU has it (SPHEREJAX_FUSED=portable)
  // Per image and band: a = c1 p + c2 and c = c3 p + c4, so v_tilde = a v + c.
  const float* gain;
  const float* offset;
  const uint8_t* image_bad;  // per image: QUALITY 8 when some p is not finite
  const Vec* projection;     // (bands, 3) vectors: the (B, 34) matrix padded to 48 columns
  const Vec* bias;           // 3 vectors: the (34,) bias [r0 | r0 @ weights] padded to 48
  float inverse_white[3];
  float* reflectance;
  float* lab;
  uint8_t* quality;
};

// x^(1/3) for x > 0: an exponent-dividing first guess (within 4 %), then two Halley steps
// y <- y (y^3 + 2x) / (2 y^3 + x), each cubing the relative error: within 3 ulp in float32
// (tests/test_fused.py).
// Written out because libm's cbrtf does not vectorise.
SPHEREJAX_INLINE float cube_root_positive(float x) {
  uint32_t bits;
  std::memcpy(&bits, &x, sizeof bits);
  bits = bits / 3u + 0x2a5137a0u;
  float y;
  std::memcpy(&y, &bits, sizeof y);
  for (int step = 0; step < 2; ++step) {
    const float y3 = y * y * y;
    y = y * (y3 + 2.0f * x) / (2.0f * y3 + x);
  }
  return y;
}

SPHEREJAX_INLINE float lab_f(float t) {
  const bool above = t > kLabEpsilon;
  const float root = cube_root_positive(above ? t : 1.0f);
  return above ? root : (kLabKappa / 116.0f) * t + 16.0f / 116.0f;
}

// Quality bits and v_tilde (Eq. 10, 17, 23) of one pixel, any band count.
template <typename Raw>
SPHEREJAX_INLINE uint8_t pixel_stage2(const Problem& pr, const Raw* r, const float* d, const float* w,
                                      const float* a, const float* c, float* tilde) {
  int32_t bits = 0;
  for (int64_t b = 0; b < pr.bands; ++b) {
    const float value = static_cast<float>(r[b]);
    const float signal = w[b] - d[b];
    const bool value_finite = std::isfinite(value);
    const bool flat_field_ok = (signal > 0.0f) & std::isfinite(signal);
    const float v = (value - d[b]) / signal;
    bits |= (value_finite & (value >= pr.saturation)) | (!value_finite << 1) | (!flat_field_ok << 2) |
            ((value_finite & flat_field_ok & (v < -kBelowDarkLimit)) << 4);
    tilde[b] = a[b] * v + c[b];
  }
  return static_cast<uint8_t>(bits);
}

#if defined(__x86_64__) && defined(__GNUC__)
#define SPHEREJAX_AVX512 1
#define SPHEREJAX_AVX512_TARGET __attribute__((target("avx512f,avx512bw,avx512dq,avx512vl,fma")))

// The same for 16 bands (the instrument's) on AVX-512: one register a quantity, the flags as
// mask registers. Written with intrinsics because GCC turns vector-extension comparisons into
// scalar code (measured: the generic loop above took 2x longer per pixel).
template <typename Raw>
SPHEREJAX_AVX512_TARGET inline uint8_t pixel_stage2_16(const Problem& pr, const Raw* r, const float* d,
                                                       const float* w, const float* a, const float* c,
                                                       float* tilde) {
  __m512 value;
  if constexpr (std::is_same_v<Raw, uint16_t>) {
    const __m256i counts = _mm256_loadu_si256(reinterpret_cast<const __m256i*>(r));
    value = _mm512_cvtepi32_ps(_mm512_cvtepu16_epi32(counts));
  } else {
    value = _mm512_loadu_ps(r);
  }
  const __m512 zero = _mm512_setzero_ps();
  const __m512 dark = _mm512_loadu_ps(d);
  const __m512 signal = _mm512_sub_ps(_mm512_loadu_ps(w), dark);
  // x - x == 0 exactly when x is finite.
  const __mmask16 value_finite = _mm512_cmp_ps_mask(_mm512_sub_ps(value, value), zero, _CMP_EQ_OQ);
  const __mmask16 saturated =
      _mm512_mask_cmp_ps_mask(value_finite, value, _mm512_set1_ps(pr.saturation), _CMP_GE_OQ);
  const __mmask16 flat_field_ok =
      _mm512_cmp_ps_mask(signal, zero, _CMP_GT_OQ) &
      _mm512_cmp_ps_mask(_mm512_sub_ps(signal, signal), zero, _CMP_EQ_OQ);
  const __m512 v = _mm512_div_ps(_mm512_sub_ps(value, dark), signal);
  const __mmask16 below_dark =
      _mm512_mask_cmp_ps_mask(flat_field_ok & value_finite, v, _mm512_set1_ps(-kBelowDarkLimit), _CMP_LT_OQ);
  _mm512_store_ps(tilde, _mm512_fmadd_ps(_mm512_loadu_ps(a), v, _mm512_loadu_ps(c)));
  return static_cast<uint8_t>((saturated != 0) | ((value_finite != 0xFFFF) << 1) |
                              ((flat_field_ok != 0xFFFF) << 2) | ((below_dark != 0) << 4));
}
#endif

// One block of up to kBlock pixels starting at `first` (flat over images and pixels).
// kAvx512: 16 bands, and the caller is compiled for AVX-512.
template <typename Raw, bool kAvx512>
SPHEREJAX_INLINE void correct_block(const Problem& pr, int64_t first, int64_t count) {
  const Raw* raw = static_cast<const Raw*>(pr.raw);
  const int64_t B = kAvx512 ? kLanes : pr.bands;
  alignas(64) float xyz[3][kBlock];
  alignas(64) float tilde[kMaxBands];
  uint8_t quality[kBlock];
  // (image, pixel) of the block's first pixel; later ones step on without a division.
  int64_t image = first / pr.pixels, pixel = first - image * pr.pixels;
  const int64_t first_image = image, first_pixel = pixel;
  for (int64_t i = 0; i < kBlock; ++i) {
    // Padding pixels of the last block repeat the block's first pixel: same code, no output.
    if (i == count) image = first_image, pixel = first_pixel;
    const int64_t flat = image * pr.pixels + pixel;
    const Raw* r = raw + flat * B;
    const float *d = pr.dark + pixel * B, *w = pr.white + pixel * B;
    const float *a = pr.gain + image * B, *c = pr.offset + image * B;
    uint8_t q;
#if SPHEREJAX_AVX512
    if constexpr (kAvx512) {
      q = pixel_stage2_16<Raw>(pr, r, d, w, a, c, tilde);
    } else {
      q = pixel_stage2<Raw>(pr, r, d, w, a, c, tilde);
    }
#else
    q = pixel_stage2<Raw>(pr, r, d, w, a, c, tilde);
#endif
    q |= pr.image_bad[image] * 8;
    quality[i] = q;
    // A bad pixel goes on as NaN, which NaN x anything carries into every output.
    if (q) std::fill(tilde, tilde + B, NAN);
    // Separate accumulators for even and odd bands halve the chain of dependent FMAs; named
    // variables, not an array, so that they stay in registers. The even ones start at the bias
    // (the estimator's offset): no extra operation per pixel, and a zero bias gives the bits of
    // a zero start. A bad pixel's NaN still reaches every output (NaN + bias is NaN).
    Vec even0 = pr.bias[0], even1 = pr.bias[1], even2 = pr.bias[2], odd0 = {}, odd1 = {}, odd2 = {};
    int64_t b = 0;
#pragma GCC unroll 8
    for (; b + 1 < B; b += 2) {
      const Vec* m = pr.projection + 3 * b;
      const float s = tilde[b], t = tilde[b + 1];
      even0 += s * m[0], even1 += s * m[1], even2 += s * m[2];
      odd0 += t * m[3], odd1 += t * m[4], odd2 += t * m[5];
    }
    if (b < B) {
      const Vec* m = pr.projection + 3 * b;
      even0 += tilde[b] * m[0], even1 += tilde[b] * m[1], even2 += tilde[b] * m[2];
    }
    const Vec out0 = even0 + odd0, out1 = even1 + odd1, out2 = even2 + odd2;
    if (i < count) {
      float* out = pr.reflectance + flat * kReflectance;
      std::memcpy(out, &out0, sizeof(Vec));
      std::memcpy(out + kLanes, &out1, (kReflectance - kLanes) * sizeof(float));
    }
    xyz[0][i] = out1[kReflectance - kLanes];
    xyz[1][i] = out2[0];
    xyz[2][i] = out2[1];
    if (i < count && ++pixel == pr.pixels) pixel = 0, ++image;
  }
  alignas(64) float lab[3][kBlock];
  for (int64_t i = 0; i < kBlock; ++i) {
    const float fx = lab_f(xyz[0][i] * pr.inverse_white[0]);
    const float fy = lab_f(xyz[1][i] * pr.inverse_white[1]);
    const float fz = lab_f(xyz[2][i] * pr.inverse_white[2]);
    lab[0][i] = 116.0f * fy - 16.0f;
    lab[1][i] = 500.0f * (fx - fy);
    lab[2][i] = 200.0f * (fy - fz);
  }
  for (int64_t i = 0; i < count; ++i) {
    float* out = pr.lab + (first + i) * 3;
    out[0] = lab[0][i];
    out[1] = lab[1][i];
    out[2] = lab[2][i];
    pr.quality[first + i] = quality[i];
  }
}

#if defined(__x86_64__) && defined(__GNUC__)
#define SPHEREJAX_AVX2 1
#define SPHEREJAX_AVX2_TARGET __attribute__((target("avx2,fma")))

// 16 bands on AVX2 (x86-64-v3), written with intrinsics: the generic code above, compiled for
// this target, keeps its 16-float vectors as pairs of ymm registers that GCC spills to the stack
// around every FMA (measured: 4x slower than the jax.numpy path on a 2-core AVX2 EPYC). The same
// equations; the sums run in another order than the generic code's (see correct_block_avx2_16).
template <typename Raw>
SPHEREJAX_AVX2_TARGET inline uint8_t pixel_stage2_16_avx2(const Problem& pr, const Raw* r, const float* d,
                                                          const float* w, const float* a, const float* c,
                                                          float* tilde) {
  const __m256 zero = _mm256_setzero_ps();
  const __m256 saturation = _mm256_set1_ps(pr.saturation);
  const __m256 infinity = _mm256_set1_ps(INFINITY);
  // The flags of both halves as lane masks, turned into bits once.
  __m256 saturated = zero, value_finite = _mm256_cmp_ps(zero, zero, _CMP_EQ_OQ), flat_field_ok = value_finite;
  __m256 below_dark = zero;
  for (int half = 0; half < 2; ++half) {
    const int64_t o = 8 * half;
    __m256 value, finite = _mm256_cmp_ps(zero, zero, _CMP_EQ_OQ);  // lanes of finite raw values
    if constexpr (std::is_same_v<Raw, uint16_t>) {
      const __m128i counts = _mm_loadu_si128(reinterpret_cast<const __m128i*>(r + o));
      value = _mm256_cvtepi32_ps(_mm256_cvtepu16_epi32(counts));
      // A count is finite: no check.
      saturated = _mm256_or_ps(saturated, _mm256_cmp_ps(value, saturation, _CMP_GE_OQ));
    } else {
      value = _mm256_loadu_ps(r + o);
      // x - x == 0 exactly when x is finite.
      finite = _mm256_cmp_ps(_mm256_sub_ps(value, value), zero, _CMP_EQ_OQ);
      value_finite = _mm256_and_ps(value_finite, finite);
      saturated = _mm256_or_ps(saturated, _mm256_and_ps(finite, _mm256_cmp_ps(value, saturation, _CMP_GE_OQ)));
    }
    const __m256 dark = _mm256_loadu_ps(d + o);
    const __m256 signal = _mm256_sub_ps(_mm256_loadu_ps(w + o), dark);
    // 0 < signal < inf: positive and finite (NaN fails both).
    const __m256 band_ok = _mm256_and_ps(_mm256_cmp_ps(signal, zero, _CMP_GT_OQ), _mm256_cmp_ps(signal, infinity, _CMP_LT_OQ));
    flat_field_ok = _mm256_and_ps(flat_field_ok, band_ok);
    const __m256 v = _mm256_div_ps(_mm256_sub_ps(value, dark), signal);
    below_dark = _mm256_or_ps(below_dark, _mm256_and_ps(_mm256_and_ps(band_ok, finite),
                                                         _mm256_cmp_ps(v, _mm256_set1_ps(-kBelowDarkLimit), _CMP_LT_OQ)));
    _mm256_store_ps(tilde + o, _mm256_fmadd_ps(_mm256_loadu_ps(a + o), v, _mm256_loadu_ps(c + o)));
  }
  return static_cast<uint8_t>((_mm256_movemask_ps(saturated) != 0) | ((_mm256_movemask_ps(value_finite) != 0xFF) << 1) |
                              ((_mm256_movemask_ps(flat_field_ok) != 0xFF) << 2) |
                              ((_mm256_movemask_ps(below_dark) != 0) << 4));
}

// lab_f of N vectors of 8 values, without a division: the cube root of x as x y^2, where y = x^(-1/3) comes
// from an exponent-dividing first guess (within 3.5 %: magic - bits / 3, the bits divided in
// float, exact enough for a guess) and two Newton steps y <- y (4 - x y^3) / 3, then one Newton
// step on the root itself, c <- c + (x - c^3) y^2 / 3 (y^2 ~ 1 / c^2). Within 1 ulp of the
// correctly rounded cube root over Lab's range (checked against float64 in
// tests/test_fused.py). The scalar `lab_f` divides (two Halley steps); this takes products
// only, which pipeline where divisions do not.
//
// N vectors at a time, each step written for all of them before the next: the steps of one
// vector depend on each other (about 20 operations in a row), so it takes several vectors side
// by side to keep the FMA units busy (measured: six vectors, 16 pixels' X, Y and Z, against
// three: 65 -> 63 ns a pixel in all, one thread of a Zen 1 EPYC).
template <int N>
SPHEREJAX_AVX2_TARGET inline void lab_f_avx2(__m256 (&t)[N]) {
  const __m256 third = _mm256_set1_ps(1.0f / 3.0f), four = _mm256_set1_ps(4.0f);
  __m256 above[N], x[N], y[N], y2[N], root[N];
  for (int k = 0; k < N; ++k) {
    above[k] = _mm256_cmp_ps(t[k], _mm256_set1_ps(kLabEpsilon), _CMP_GT_OQ);
    x[k] = _mm256_blendv_ps(_mm256_set1_ps(1.0f), t[k], above[k]);
    const __m256i bits_third = _mm256_cvtps_epi32(_mm256_mul_ps(_mm256_cvtepi32_ps(_mm256_castps_si256(x[k])), third));
    y[k] = _mm256_castsi256_ps(_mm256_sub_epi32(_mm256_set1_epi32(0x54a232a0), bits_third));
  }
  for (int step = 0; step < 2; ++step) {
    for (int k = 0; k < N; ++k) {
      // x y^3 as (x y) y^2: two products side by side, not three in a row.
      const __m256 reduced = _mm256_fnmadd_ps(_mm256_mul_ps(x[k], y[k]), _mm256_mul_ps(y[k], y[k]), four);
      y[k] = _mm256_mul_ps(_mm256_mul_ps(y[k], third), reduced);
    }
  }
  for (int k = 0; k < N; ++k) {
    y2[k] = _mm256_mul_ps(y[k], y[k]);
    root[k] = _mm256_mul_ps(x[k], y2[k]);
  }
  for (int k = 0; k < N; ++k) {
    const __m256 residual = _mm256_fnmadd_ps(_mm256_mul_ps(root[k], root[k]), root[k], x[k]);
    root[k] = _mm256_fmadd_ps(_mm256_mul_ps(residual, y2[k]), third, root[k]);
    const __m256 linear = _mm256_fmadd_ps(_mm256_set1_ps(kLabKappa / 116.0f), t[k], _mm256_set1_ps(16.0f / 116.0f));
    t[k] = _mm256_blendv_ps(linear, root[k], above[k]);
  }
}

// A value the compiler must keep in a register, not fold into the instructions that use it:
// for a matrix row loaded once and shared by two FMAs, which GCC otherwise turns into two FMAs
// with a memory operand each, loading the row twice and undoing the sharing (measured: the
// loads then bound the projection).
template <typename V>
SPHEREJAX_AVX2_TARGET inline V in_register(V v) {
  __asm__("" : "+x"(v));
  return v;
}

// Lane 7 of a ymm register as a scalar.
SPHEREJAX_AVX2_TARGET inline float lane7(__m256 v) {
  return _mm_cvtss_f32(_mm_permute_ps(_mm256_extractf128_ps(v, 1), 3));
}

// One block of 32 pixels in three passes: quality and v_tilde of every pixel; the projection,
// two pixels at a time; Lab, sixteen at a time.
// (On a 2-core first-generation EPYC, whose ymm operations are two 128-bit halves: 83 -> 60-65
// ns a pixel on one thread against the one-pixel loop with the Halley root, which this replaced.)
//
// The projection of a pixel is 16 broadcasts of its v_tilde times the matrix rows, into 34
// accumulator lanes: four ymm (reflectance 0..30, X) and one xmm (Y, Z, padding), 9 register
// FMAs a band where five ymm took 10. Two pixels share each row load (10 accumulators, 3
// temporaries: 13 of the 16 ymm registers), halving the loads, which bound the one-pixel loop
// (80 row loads and 16 broadcasts against 80 FMAs a pixel). Each accumulator starts at the bias
// (the estimator's offset): a zero bias gives the bits of a zero start. The sums' order depends
// only on the pixel, never on its partner or place in the block, so strips give the bits of the
// whole image.
//
// Stores: a block's reflectance (32 pixels x 31 floats = 124 whole ymm), Lab (12 ymm) and
// quality (one ymm) are contiguous and 32-byte aligned when the block starts at a multiple of 32
// pixels of an aligned buffer, so they are written with non-temporal stores: the outputs are
// written whole and never read back here, and ordinary stores would first read every cache line
// they overwrite (a read of 136 bytes a pixel that the path does not need). Other blocks (the
// last, partial one) take ordinary stores.
template <typename Raw>
SPHEREJAX_AVX2_TARGET inline void correct_block_avx2_16(const Problem& pr, int64_t first, int64_t count) {
  const Raw* raw = static_cast<const Raw*>(pr.raw);
  constexpr int64_t B = kLanes;
  // Room beyond the block (one float is needed): pixel i's 32-float store spills its X into pixel
  // i + 1's first slot, which pixel i + 1 then overwrites; the last pixel's lands here.
  alignas(32) float reflectance[kBlock * kReflectance + 8];
  alignas(32) float xyz[3][kBlock];
  alignas(32) float tilde[kBlock][B];
  alignas(32) uint8_t quality[kBlock];
  int64_t image = first / pr.pixels, pixel = first - image * pr.pixels;
  const int64_t first_image = image, first_pixel = pixel;
  for (int64_t i = 0; i < kBlock; ++i) {
    if (i == count) image = first_image, pixel = first_pixel;  // padding repeats the first pixel
    const int64_t flat = image * pr.pixels + pixel;
    uint8_t q = pixel_stage2_16_avx2<Raw>(pr, raw + flat * B, pr.dark + pixel * B, pr.white + pixel * B,
                                          pr.gain + image * B, pr.offset + image * B, tilde[i]);
    q |= pr.image_bad[image] * 8;
    quality[i] = q;
    // A bad pixel goes on as NaN, which NaN x anything carries into every output.
    if (q) std::fill(tilde[i], tilde[i] + B, NAN);
    if (i < count && ++pixel == pr.pixels) pixel = 0, ++image;
  }
  // Columns 0..35 of the (B, 48) matrix and bias: 31 reflectances, X, Y, Z, padding.
  const float* projection = reinterpret_cast<const float*>(pr.projection);
  const float* bias = reinterpret_cast<const float*>(pr.bias);
  for (int64_t i = 0; i < kBlock; i += 2) {
    __m256 a0 = _mm256_load_ps(bias), a1 = _mm256_load_ps(bias + 8), a2 = _mm256_load_ps(bias + 16),
           a3 = _mm256_load_ps(bias + 24);
    __m128 a4 = _mm_load_ps(bias + 32);
    __m256 b0 = a0, b1 = a1, b2 = a2, b3 = a3;
    __m128 b4 = a4;
#pragma GCC unroll 16
    for (int64_t b = 0; b < B; ++b) {
      const float* m = projection + b * kPadded;
      const __m256 s = _mm256_broadcast_ss(&tilde[i][b]), t = _mm256_broadcast_ss(&tilde[i + 1][b]);
      __m256 row = in_register(_mm256_load_ps(m));
      a0 = _mm256_fmadd_ps(s, row, a0), b0 = _mm256_fmadd_ps(t, row, b0);
      row = in_register(_mm256_load_ps(m + 8));
      a1 = _mm256_fmadd_ps(s, row, a1), b1 = _mm256_fmadd_ps(t, row, b1);
      row = in_register(_mm256_load_ps(m + 16));
      a2 = _mm256_fmadd_ps(s, row, a2), b2 = _mm256_fmadd_ps(t, row, b2);
      row = in_register(_mm256_load_ps(m + 24));
      a3 = _mm256_fmadd_ps(s, row, a3), b3 = _mm256_fmadd_ps(t, row, b3);
      const __m128 tail = in_register(_mm_load_ps(m + 32));
      a4 = _mm_fmadd_ps(_mm256_castps256_ps128(s), tail, a4);
      b4 = _mm_fmadd_ps(_mm256_castps256_ps128(t), tail, b4);
    }
    float* out = reflectance + i * kReflectance;
    _mm256_storeu_ps(out, a0), _mm256_storeu_ps(out + 8, a1), _mm256_storeu_ps(out + 16, a2);
    _mm256_storeu_ps(out + 24, a3);  // lane 7, X, is overwritten by the next pixel's first store
    _mm256_storeu_ps(out + kReflectance, b0), _mm256_storeu_ps(out + kReflectance + 8, b1);
    _mm256_storeu_ps(out + kReflectance + 16, b2), _mm256_storeu_ps(out + kReflectance + 24, b3);
    xyz[0][i] = lane7(a3), xyz[0][i + 1] = lane7(b3);
    xyz[1][i] = _mm_cvtss_f32(a4), xyz[1][i + 1] = _mm_cvtss_f32(b4);
    xyz[2][i] = _mm_cvtss_f32(_mm_movehdup_ps(a4)), xyz[2][i + 1] = _mm_cvtss_f32(_mm_movehdup_ps(b4));
  }
  alignas(32) float lab[kBlock * 3];
  for (int64_t i = 0; i < kBlock; i += 16) {
    // f(X / Xn), f(Y / Yn), f(Z / Zn) of pixels i..i+7 and i+8..i+15, side by side.
    __m256 f[6];
    for (int k = 0; k < 3; ++k) {
      const __m256 inverse_white = _mm256_set1_ps(pr.inverse_white[k]);
      f[2 * k] = _mm256_mul_ps(_mm256_load_ps(xyz[k] + i), inverse_white);
      f[2 * k + 1] = _mm256_mul_ps(_mm256_load_ps(xyz[k] + i + 8), inverse_white);
    }
    lab_f_avx2(f);
    for (int half = 0; half < 2; ++half) {
      const __m256 fx = f[half], fy = f[2 + half], fz = f[4 + half];
      const __m256 l = _mm256_fmsub_ps(_mm256_set1_ps(116.0f), fy, _mm256_set1_ps(16.0f));
      const __m256 a = _mm256_mul_ps(_mm256_set1_ps(500.0f), _mm256_sub_ps(fx, fy));
      const __m256 b = _mm256_mul_ps(_mm256_set1_ps(200.0f), _mm256_sub_ps(fy, fz));
      // Interleave to L a b L a b ... in each 128-bit lane (four of the eight pixels each): in-lane
      // shuffles only, which cost one operation a lane on every AVX2 CPU.
      const __m256 la_lo = _mm256_unpacklo_ps(l, a), la_hi = _mm256_unpackhi_ps(l, a);  // L0 a0 L1 a1 | L2 a2 L3 a3
      const __m256 bl_lo = _mm256_unpacklo_ps(b, l), bl_hi = _mm256_unpackhi_ps(b, l);  // b0 L0 b1 L1 | b2 L2 b3 L3
      const __m256 ab_lo = _mm256_unpacklo_ps(a, b), ab_hi = _mm256_unpackhi_ps(a, b);  // a0 b0 a1 b1 | a2 b2 a3 b3
      const __m256 first4 = _mm256_shuffle_ps(la_lo, bl_lo, _MM_SHUFFLE(3, 0, 1, 0));   // L0 a0 b0 L1
      const __m256 middle4 = _mm256_shuffle_ps(ab_lo, la_hi, _MM_SHUFFLE(1, 0, 3, 2));  // a1 b1 L2 a2
      const __m256 last4 = _mm256_shuffle_ps(bl_hi, ab_hi, _MM_SHUFFLE(3, 2, 3, 0));    // b2 L3 a3 b3
      float* out = lab + 3 * (i + 8 * half);
      _mm_store_ps(out, _mm256_castps256_ps128(first4));
      _mm_store_ps(out + 4, _mm256_castps256_ps128(middle4));
      _mm_store_ps(out + 8, _mm256_castps256_ps128(last4));
      _mm_store_ps(out + 12, _mm256_extractf128_ps(first4, 1));
      _mm_store_ps(out + 16, _mm256_extractf128_ps(middle4, 1));
      _mm_store_ps(out + 20, _mm256_extractf128_ps(last4, 1));
    }
  }
  float* reflectance_out = pr.reflectance + first * kReflectance;
  float* lab_out = pr.lab + first * 3;
  uint8_t* quality_out = pr.quality + first;
  const bool streamable = count == kBlock && (reinterpret_cast<uintptr_t>(reflectance_out) % 32 == 0) &&
                          (reinterpret_cast<uintptr_t>(lab_out) % 32 == 0) &&
                          (reinterpret_cast<uintptr_t>(quality_out) % 32 == 0);
  if (streamable) {
    for (int64_t k = 0; k < kBlock * kReflectance; k += 8) {
      _mm256_stream_ps(reflectance_out + k, _mm256_load_ps(reflectance + k));
    }
    for (int64_t k = 0; k < kBlock * 3; k += 8) _mm256_stream_ps(lab_out + k, _mm256_load_ps(lab + k));
    _mm256_stream_si256(reinterpret_cast<__m256i*>(quality_out), _mm256_load_si256(reinterpret_cast<const __m256i*>(quality)));
  } else {
    std::memcpy(reflectance_out, reflectance, count * kReflectance * sizeof(float));
    std::memcpy(lab_out, lab, count * 3 * sizeof(float));
    std::memcpy(quality_out, quality, count);
  }
}

SPHEREJAX_AVX2_TARGET __attribute__((flatten)) void correct_range_16_avx2_u16(const Problem& pr, int64_t first, int64_t last) {
  for (int64_t block = first; block < last; block += kBlock) {
    correct_block_avx2_16<uint16_t>(pr, block, std::min(kBlock, last - block));
  }
  _mm_sfence();  // the non-temporal stores are visible before the chunk is counted as finished
}
SPHEREJAX_AVX2_TARGET __attribute__((flatten)) void correct_range_16_avx2_f32(const Problem& pr, int64_t first, int64_t last) {
  for (int64_t block = first; block < last; block += kBlock) {
    correct_block_avx2_16<float>(pr, block, std::min(kBlock, last - block));
  }
  _mm_sfence();
}
#endif

template <typename Raw, bool kAvx512>
SPHEREJAX_INLINE void correct_range_body(const Problem& pr, int64_t first, int64_t last) {
  for (int64_t block = first; block < last; block += kBlock) {
    correct_block<Raw, kAvx512>(pr, block, std::min(kBlock, last - block));
  }
}

// The generic kernel, compiled for three x86-64 levels and picked at load time (target_clones).
SPHEREJAX_CLONES void correct_range_u16(const Problem& pr, int64_t first, int64_t last) {
  correct_range_body<uint16_t, false>(pr, first, last);
}
SPHEREJAX_CLONES void correct_range_f32(const Problem& pr, int64_t first, int64_t last) {
  correct_range_body<float, false>(pr, first, last);
}

#if SPHEREJAX_AVX512
// flatten: inline everything, pixel_stage2_16 included, which the always_inline chain cannot
// (a default-target function may not inline an AVX-512 one).
SPHEREJAX_AVX512_TARGET __attribute__((flatten)) void correct_range_16_avx512_u16(const Problem& pr, int64_t first, int64_t last) {
  correct_range_body<uint16_t, true>(pr, first, last);
}
SPHEREJAX_AVX512_TARGET __attribute__((flatten)) void correct_range_16_avx512_f32(const Problem& pr, int64_t first, int64_t last) {
  correct_range_body<float, true>(pr, first, last);
}
#endif

void correct_range(const Problem& pr, int64_t first, int64_t last) {
#if SPHEREJAX_AVX512
  static const bool avx512 = __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512bw") &&
                             __builtin_cpu_supports("avx512dq") && __builtin_cpu_supports("avx512vl");
  if (avx512 && pr.bands == kLanes && !pr.portable) {
    return pr.raw_is_u16 ? correct_range_16_avx512_u16(pr, first, last)
                         : correct_range_16_avx512_f32(pr, first, last);
  }
#endif
#if SPHEREJAX_AVX2
  static const bool avx2 = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
  if (avx2 && pr.bands == kLanes) {
    return pr.raw_is_u16 ? correct_range_16_avx2_u16(pr, first, last)
                         : correct_range_16_avx2_f32(pr, first, last);
  }
#endif
  return pr.raw_is_u16 ? correct_range_u16(pr, first, last) : correct_range_f32(pr, first, last);
}

// Chunks handed out by an atomic counter to the calling thread and to tasks on XLA's pool.
// The state is shared-owned: a task the pool starts late finds no chunk left and only drops
// its reference.
struct Shared {
  Problem problem;
  int64_t chunks = 0;
  std::atomic<int64_t> next{0};
  std::atomic<int64_t> finished{0};
  std::mutex mutex;
  std::condition_variable all_done;

  void work() {
    const int64_t total = problem.images * problem.pixels;
    for (int64_t chunk; (chunk = next.fetch_add(1)) < chunks;) {
      const int64_t first = chunk * kChunk, last = std::min(total, first + kChunk);
      correct_range(problem, first, last);
      if (finished.fetch_add(1) + 1 == chunks) {
        std::lock_guard<std::mutex> lock(mutex);
        all_done.notify_all();
      }
    }
  }
};

// One call's Problem and the arrays it points to besides the caller's: the per-image gains,
// offsets and flags, and the projection and bias padded to whole vectors. Layouts as in the
// header of this file.
struct FreeAligned {
  void operator()(float* p) const { std::free(p); }
};
// `count` vectors on a 64-byte boundary, which the aligned loads of the projection rows need.
// (Not std::unique_ptr<Vec[]> members: GCC warns that a template argument drops Vec's alignment
// attribute; an explicit aligned_alloc does not depend on what the compiler keeps of it.)
std::unique_ptr<float[], FreeAligned> aligned_vectors(int64_t count) {
  return std::unique_ptr<float[], FreeAligned>(
      static_cast<float*>(std::aligned_alloc(64, std::max<int64_t>(count, 1) * sizeof(Vec))));
}

struct Prepared {
  std::shared_ptr<Shared> shared = std::make_shared<Shared>();
  std::unique_ptr<float[]> gain, offset;
  std::unique_ptr<uint8_t[]> image_bad;
  std::unique_ptr<float[], FreeAligned> padded, padded_bias;
};

std::unique_ptr<Prepared> prepare(const void* raw, bool u16, const float* dark, const float* white,
                                  const float* ratio, const float* c, const float* m,
                                  const float* offsets, const float* wxyz, int64_t images, int64_t pixels,
                                  int64_t bands, float saturation, bool portable, float* reflectance,
                                  float* lab, uint8_t* quality) {
  auto prepared = std::make_unique<Prepared>();
  prepared->gain = std::make_unique<float[]>(images * bands);
  prepared->offset = std::make_unique<float[]>(images * bands);
  prepared->image_bad = std::make_unique<uint8_t[]>(images);
  prepared->padded = aligned_vectors(3 * bands);
  prepared->padded_bias = aligned_vectors(3);
  if (!prepared->padded || !prepared->padded_bias) throw std::bad_alloc();
  float* gain = prepared->gain.get();
  float* offset = prepared->offset.get();
  for (int64_t n = 0; n < images; ++n) {
    bool bad = false;
    for (int64_t b = 0; b < bands; ++b) {
      const float pb = ratio[n * bands + b];
      bad |= !std::isfinite(pb);
      gain[n * bands + b] = c[4 * b + 0] * pb + c[4 * b + 1];
      offset[n * bands + b] = c[4 * b + 2] * pb + c[4 * b + 3];
    }
    prepared->image_bad[n] = bad;
  }
  for (int64_t b = 0; b < bands; ++b) {
    float* row = prepared->padded.get() + 3 * kLanes * b;
    for (int64_t k = 0; k < kPadded; ++k) row[k] = k < kOutputs ? m[b * kOutputs + k] : 0.0f;
  }
  float* bias_row = prepared->padded_bias.get();
  for (int64_t k = 0; k < kPadded; ++k) bias_row[k] = k < kOutputs ? offsets[k] : 0.0f;

  Problem& pr = prepared->shared->problem;
  pr.raw = raw;
  pr.raw_is_u16 = u16;
  pr.dark = dark;
  pr.white = white;
  pr.images = images;
  pr.pixels = pixels;
  pr.bands = bands;
  pr.saturation = saturation;
  pr.portable = portable;
  pr.gain = gain;
  pr.offset = offset;
  pr.image_bad = prepared->image_bad.get();
  pr.projection = reinterpret_cast<const Vec*>(prepared->padded.get());
  pr.bias = reinterpret_cast<const Vec*>(prepared->padded_bias.get());
  for (int k = 0; k < 3; ++k) pr.inverse_white[k] = 1.0f / wxyz[k];
  pr.reflectance = reflectance;
  pr.lab = lab;
  pr.quality = quality;
  prepared->shared->chunks = (images * pixels + kChunk - 1) / kChunk;
  return prepared;
}

// Runs the chunks on the calling thread and whatever helpers `schedule` started, then waits for
// the last chunk.
template <typename Schedule>
void run(Shared& shared, Schedule schedule) {
  schedule();
  shared.work();
  std::unique_lock<std::mutex> lock(shared.mutex);
  shared.all_done.wait(lock, [&] { return shared.finished.load() == shared.chunks; });
}

ffi::Error Correct(ffi::ThreadPool pool, ffi::AnyBuffer raw, ffi::Buffer<ffi::F32> dark,
                   ffi::Buffer<ffi::F32> white, ffi::Buffer<ffi::F32> p,
                   ffi::Buffer<ffi::F32> coeffs, ffi::Buffer<ffi::F32> projection,
                   ffi::Buffer<ffi::F32> bias, ffi::Buffer<ffi::F32> white_xyz, float saturation, int32_t portable,
                   ffi::ResultBuffer<ffi::F32> reflectance, ffi::ResultBuffer<ffi::F32> lab,
                   ffi::ResultBuffer<ffi::U8> quality) {
  const auto dims = raw.dimensions();
  if (dims.size() != 3) return ffi::Error::InvalidArgument("raw: expected (N, P, B)");
  const int64_t images = dims[0], pixels = dims[1], bands = dims[2];
  const bool u16 = raw.element_type() == ffi::U16;
  if (!u16 && raw.element_type() != ffi::F32) {
    return ffi::Error::InvalidArgument("raw: expected uint16 or float32");
  }
  if (bands < 1 || bands > kMaxBands) return ffi::Error::InvalidArgument("bands: expected 1..64");
  if (dark.element_count() != size_t(pixels * bands) || white.element_count() != dark.element_count() ||
      p.element_count() != size_t(images * bands) || coeffs.element_count() != size_t(bands * 4) ||
      projection.element_count() != size_t(bands * kOutputs) || bias.element_count() != size_t(kOutputs) ||
      white_xyz.element_count() != 3) {
    return ffi::Error::InvalidArgument("inputs: shapes do not match raw (N, P, B)");
  }
  std::unique_ptr<Prepared> prepared;
  try {
    prepared = prepare(raw.untyped_data(), u16, dark.typed_data(), white.typed_data(), p.typed_data(),
                          coeffs.typed_data(), projection.typed_data(), bias.typed_data(), white_xyz.typed_data(),
                          images, pixels, bands, saturation, portable != 0, reflectance->typed_data(),
                          lab->typed_data(), quality->typed_data());
  } catch (const std::bad_alloc&) {
    return ffi::Error(ffi::ErrorCode::kResourceExhausted, "out of memory");
  }
  std::shared_ptr<Shared> shared = prepared->shared;
  run(*shared, [&] {
    const int64_t helpers = std::min<int64_t>(pool.num_threads(), shared->chunks - 1);
    for (int64_t t = 0; t < helpers; ++t) pool.Schedule([shared] { shared->work(); });
  });
  return ffi::Error::Success();
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(SpherejaxFusedCorrect, Correct,
                              ffi::Ffi::Bind()
                                  .Ctx<ffi::ThreadPool>()
                                  .Arg<ffi::AnyBuffer>()           // raw
                                  .Arg<ffi::Buffer<ffi::F32>>()    // dark
                                  .Arg<ffi::Buffer<ffi::F32>>()    // white
                                  .Arg<ffi::Buffer<ffi::F32>>()    // p
                                  .Arg<ffi::Buffer<ffi::F32>>()    // coeffs
                                  .Arg<ffi::Buffer<ffi::F32>>()    // projection
                                  .Arg<ffi::Buffer<ffi::F32>>()    // bias
                                  .Arg<ffi::Buffer<ffi::F32>>()    // white_xyz
                                  .Attr<float>("saturation")
                                  .Attr<int32_t>("portable")
                                  .Ret<ffi::Buffer<ffi::F32>>()    // reflectance
                                  .Ret<ffi::Buffer<ffi::F32>>()    // lab
                                  .Ret<ffi::Buffer<ffi::U8>>());   // quality

// A Python module with one function, handler(), returning the FFI handler as a capsule for
// jax.ffi.register_ffi_target (spherejax/_engine/fused.py).
static PyObject* handler(PyObject*, PyObject*) {
  return PyCapsule_New(reinterpret_cast<void*>(&SpherejaxFusedCorrect), nullptr, nullptr);
}

// correct_arrays(raw, raw_is_u16, dark, white, p, coeffs, projection, bias, white_xyz, images,
// pixels, bands, saturation, portable, threads, reflectance, lab, quality): the same kernel on
// C-contiguous buffers from Python, run by the calling thread and threads - 1 helpers, without
// XLA. spherejax._engine.fused.correct_arrays checks dtypes; this checks each buffer's byte size, so
// that nothing is read or written outside a buffer. Releases the GIL while it runs.
static PyObject* correct_arrays(PyObject*, PyObject* args) {
  Py_buffer in[8] = {}, out[3] = {};
  int u16 = 0, portable = 0;
  long long images = 0, pixels = 0, bands = 0;
  float saturation = 0.0f;
  Py_ssize_t threads = 1;
  if (!PyArg_ParseTuple(args, "y*py*y*y*y*y*y*y*LLLfpnw*w*w*", &in[0], &u16, &in[1], &in[2], &in[3], &in[4],
                        &in[5], &in[6], &in[7], &images, &pixels, &bands, &saturation, &portable, &threads,
                        &out[0], &out[1], &out[2])) {
    return nullptr;  // PyArg_ParseTuple releases what it had taken
  }
  const long long expected_in[8] = {images * pixels * bands * (u16 ? 2 : 4), pixels * bands * 4,
                                    pixels * bands * 4, images * bands * 4, bands * 4 * 4,
                                    bands * kOutputs * 4, kOutputs * 4, 3 * 4};
  const long long expected_out[3] = {images * pixels * kReflectance * 4, images * pixels * 3 * 4, images * pixels};
  bool sizes_match = images >= 0 && pixels >= 0 && bands >= 1 && bands <= kMaxBands && threads >= 1;
  for (int k = 0; k < 8; ++k) sizes_match &= in[k].len == expected_in[k];
  for (int k = 0; k < 3; ++k) sizes_match &= out[k].len == expected_out[k];
  std::unique_ptr<Prepared> prepared;
  if (sizes_match && images * pixels > 0) {
    try {
      prepared = prepare(
        in[0].buf, u16 != 0, static_cast<const float*>(in[1].buf), static_cast<const float*>(in[2].buf),
        static_cast<const float*>(in[3].buf), static_cast<const float*>(in[4].buf),
        static_cast<const float*>(in[5].buf), static_cast<const float*>(in[6].buf),
        static_cast<const float*>(in[7].buf), images, pixels, bands, saturation, portable != 0,
        static_cast<float*>(out[0].buf), static_cast<float*>(out[1].buf), static_cast<uint8_t*>(out[2].buf));
    } catch (const std::bad_alloc&) {
      for (auto& buffer : in) PyBuffer_Release(&buffer);
      for (auto& buffer : out) PyBuffer_Release(&buffer);
      return PyErr_NoMemory();
    }
    Shared& shared = *prepared->shared;
    std::vector<std::thread> helpers;
    Py_BEGIN_ALLOW_THREADS
    run(shared, [&] {
      const int64_t count = std::min<int64_t>(threads - 1, shared.chunks - 1);
      try {
        for (int64_t t = 0; t < count; ++t) helpers.emplace_back([&shared] { shared.work(); });
      } catch (...) {  // std::system_error or bad_alloc: no more threads to be had
        // The threads started and this one do all the chunks.
      }
    });
    for (auto& helper : helpers) helper.join();
    Py_END_ALLOW_THREADS
  }
  for (auto& buffer : in) PyBuffer_Release(&buffer);
  for (auto& buffer : out) PyBuffer_Release(&buffer);
  if (!sizes_match) {
    PyErr_SetString(PyExc_ValueError, "correct_arrays: buffer sizes do not match images, pixels and bands");
    return nullptr;
  }
  Py_RETURN_NONE;
}

// ffi_api_version() -> (major, minor): the XLA FFI API version of the headers this was compiled
// against, which XLA compares with its own when the handler is registered (setup.py).
static PyObject* ffi_api_version(PyObject*, PyObject*) {
  return Py_BuildValue("(ii)", XLA_FFI_API_MAJOR, XLA_FFI_API_MINOR);
}

static PyMethodDef methods[] = {
    {"handler", handler, METH_NOARGS, "The XLA FFI handler of the fused correction, as a capsule."},
    {"ffi_api_version", ffi_api_version, METH_NOARGS, "The XLA FFI API version compiled against, (major, minor)."},
    {"correct_arrays", correct_arrays, METH_VARARGS, "The fused correction on C-contiguous buffers, without XLA."},
    {nullptr, nullptr, 0, nullptr},
};

static PyModuleDef module = {PyModuleDef_HEAD_INIT, "_fused_correct",
                             "Fused CPU kernel of spherejax.correct (see spherejax/_engine/fused.py).", -1,
                             methods};

PyMODINIT_FUNC PyInit__fused_correct() { return PyModule_Create(&module); }
