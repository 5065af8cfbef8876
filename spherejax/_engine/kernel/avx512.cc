// The AVX-512 variant of the kernel: 16 bands (the instrument's), the generic block of
// fused_correct.h with a Stage II and a lane policy for the kernel residual written with AVX-512
// intrinsics.

#include "fused_correct.h"

#if SPHEREJAX_X86

#include <immintrin.h>

#include <algorithm>
#include <type_traits>

namespace spherejax_fused {
namespace {

// The 16 x 16 floats at rows[k * stride] (k < 16, each row 64-byte aligned) transposed into
// out[16]: interleaves of 32 and 64 bits within 128-bit lanes, then two rounds of 128-bit lane
// shuffles (64 instructions).
SPHEREJAX_AVX512_TARGET static inline void transpose_16(const float* rows, int64_t stride, __m512* out) {
  __m512 t[16], u[16];
  for (int k = 0; k < 8; ++k) {
    const __m512 a = _mm512_load_ps(rows + 2 * k * stride), b = _mm512_load_ps(rows + (2 * k + 1) * stride);
    t[2 * k] = _mm512_unpacklo_ps(a, b);      // a0 b0 a1 b1 in each 128-bit lane
    t[2 * k + 1] = _mm512_unpackhi_ps(a, b);  // a2 b2 a3 b3
  }
  for (int k = 0; k < 4; ++k) {
    const __m512d lo0 = _mm512_castps_pd(t[4 * k]), lo1 = _mm512_castps_pd(t[4 * k + 2]);
    const __m512d hi0 = _mm512_castps_pd(t[4 * k + 1]), hi1 = _mm512_castps_pd(t[4 * k + 3]);
    u[4 * k + 0] = _mm512_castpd_ps(_mm512_unpacklo_pd(lo0, lo1));  // column 4L + 0 of rows 4k..4k+3
    u[4 * k + 1] = _mm512_castpd_ps(_mm512_unpackhi_pd(lo0, lo1));
    u[4 * k + 2] = _mm512_castpd_ps(_mm512_unpacklo_pd(hi0, hi1));
    u[4 * k + 3] = _mm512_castpd_ps(_mm512_unpackhi_pd(hi0, hi1));
  }
  for (int c = 0; c < 4; ++c) {
    const __m512 v0 = _mm512_shuffle_f32x4(u[c], u[4 + c], 0x88), v1 = _mm512_shuffle_f32x4(u[c], u[4 + c], 0xDD);
    const __m512 w0 = _mm512_shuffle_f32x4(u[8 + c], u[12 + c], 0x88);
    const __m512 w1 = _mm512_shuffle_f32x4(u[8 + c], u[12 + c], 0xDD);
    out[c] = _mm512_shuffle_f32x4(v0, w0, 0x88);
    out[c + 4] = _mm512_shuffle_f32x4(v1, w1, 0x88);
    out[c + 8] = _mm512_shuffle_f32x4(v0, w0, 0xDD);
    out[c + 12] = _mm512_shuffle_f32x4(v1, w1, 0xDD);
  }
}

// Stage II (fused_correct.h) for 16 bands on AVX-512: one register a quantity, the flags as mask
// registers. Written with intrinsics because GCC turns vector-extension comparisons into scalar
// code (measured: the generic loop took 2x longer per pixel).
struct Avx512Stage2 {
  static constexpr int64_t kBands = kLanes;

  template <typename Raw>
  SPHEREJAX_AVX512_TARGET static inline uint8_t run(const Problem& pr, const Raw* r, const float* d,
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
};

// The lane policy of the kernel residual (fused_correct.h, residual_of) on AVX-512: the generic
// one's vector (16 floats, one zmm register) and steps, with the exponential and the transposes
// written with AVX-512 intrinsics.
struct Avx512Lanes : GenericLanes {
  // 2^min(t, 0) (fused_correct.h, residual_of: e^x with x log2(e) = t folded into the
  // constants) with AVX-512's own steps: t = n + f rounded by vrndscaleps, 2^f by the AVX2 code's
  // polynomial of degree 5 (exp2_nonpositive_avx2: relative error 7.5e-8, one multiply-add fewer
  // than the Taylor polynomial of degree 6), and 2^n put in by vscalefps, which needs no bit
  // arithmetic and no clip below (n floored at -125 all the same, so that no result is
  // subnormal). 10 instructions against the generic code's 19 (measured: the exponential was a
  // quarter of the residual's time).
  SPHEREJAX_AVX512_TARGET static inline Vec exp2_lanes(Vec x) {
    const __m512 t = _mm512_max_ps(_mm512_min_ps((__m512)x, _mm512_setzero_ps()), _mm512_set1_ps(-125.0f));
    const __m512 n = _mm512_roundscale_ps(t, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
    const __m512 f = _mm512_sub_ps(t, n);
    __m512 p = _mm512_fmadd_ps(_mm512_set1_ps(1.327644451521337e-3f), f, _mm512_set1_ps(9.67553723603487e-3f));
    p = _mm512_fmadd_ps(p, f, _mm512_set1_ps(5.550713464617729e-2f));
    p = _mm512_fmadd_ps(p, f, _mm512_set1_ps(2.4022120237350464e-1f));
    p = _mm512_fmadd_ps(p, f, _mm512_set1_ps(6.931469440460205e-1f));
    p = _mm512_fmadd_ps(p, f, _mm512_set1_ps(1.0000001192092896f));
    return (Vec)_mm512_scalef_ps(p, n);
  }

  SPHEREJAX_AVX512_TARGET static inline void exp2(Vec* k, int64_t n) {
    for (int64_t j = 0; j < n; ++j) k[j] = exp2_lanes(k[j]);
  }

  // columns (fused_correct.h) for 16 bands: each 16 x 16 half of the block transposed in
  // registers (transpose_16), where element by element took 32 loads and stores a pixel.
  SPHEREJAX_AVX512_TARGET static inline void columns(const float (*rows)[kMaxBands], int64_t,
                                                     float (*columns)[kBlock]) {
    for (int64_t first = 0; first < kBlock; first += kLanes) {
      __m512 c[16];
      transpose_16(rows[first], kMaxBands, c);
      for (int b = 0; b < 16; ++b) _mm512_store_ps(columns[b] + first, c[b]);
    }
  }

  // write_rows (fused_correct.h): outputs 0-15 and 16-31 of each 16 pixels transposed in
  // registers (transpose_16), then a pixel's 31 floats as one store and one masked store.
  SPHEREJAX_AVX512_TARGET static inline void write_rows(const float (*out)[kBlock], int64_t count, float* to) {
    for (int64_t first = 0; first < count; first += kLanes) {
      __m512 low[16], high[16];
      transpose_16(out[0] + first, kBlock, low);
      transpose_16(out[kLanes] + first, kBlock, high);
      const int64_t n = std::min<int64_t>(kLanes, count - first);
      for (int64_t i = 0; i < n; ++i) {
        float* row = to + (first + i) * kReflectance;
        _mm512_storeu_ps(row, low[i]);
        _mm512_mask_storeu_ps(row + kLanes, static_cast<__mmask16>((1u << (kReflectance - kLanes)) - 1), high[i]);
      }
    }
  }
};

}  // namespace

// flatten: inline everything, Avx512Stage2::run included, which the always_inline chain cannot
// (a default-target function may not inline an AVX-512 one).
SPHEREJAX_AVX512_TARGET __attribute__((flatten)) void correct_range_avx512(const Problem& pr, int64_t first,
                                                                           int64_t last) {
  correct_blocks<PixelByPixel<Avx512Stage2, Avx512Lanes>>(pr, first, last);
}

}  // namespace spherejax_fused

#endif  // SPHEREJAX_X86
