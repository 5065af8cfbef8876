// The fast path of the band registration (band_taps.h): native rows as flat-fielded responses,
// then registered rows sampled from them with the bands of a pixel side by side.
//
// Why the bands side by side: the frames are interleaved (pixel-major, band-minor), as the fused
// correction reads them; sampling band by band along a row would need the native responses and the
// registered ones transposed into planes and back, which took two thirds of the registration's
// time in the first version (benchmarks/README.md, "Bands in register"). For 16 bands on CPUs with
// AVX-512 or AVX2, one vector holds a pixel's bands and its taps are masked loads (sample_row_16_*);
// otherwise the compiler vectorises sample_row as it can.

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "band_taps.h"

#if defined(__x86_64__) && defined(__GNUC__)
#include <immintrin.h>
#endif

namespace spherejax_bands {
namespace {

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#define SPHEREJAX_BANDS_CLONES __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define SPHEREJAX_BANDS_CLONES
#endif

// The loops are compiled without trapping math (floating-point exceptions are never unmasked
// here): otherwise GCC keeps a float-to-int conversion and the selects as branches and does not
// vectorise them.
#pragma GCC push_options
#pragma GCC optimize("no-trapping-math")

// Elements [begin, end) of one image's interleaved frames (index (y W + x) B + b) as responses.
template <typename Raw>
SPHEREJAX_BANDS_CLONES void responses(const Raw* __restrict raw, const float* __restrict dark,
                                      const float* __restrict inverse_signal, float saturation, int64_t begin,
                                      int64_t end, float* __restrict out) {
  for (int64_t i = begin; i < end; ++i) {
    const float value = static_cast<float>(raw[i]);
    const float inverse = inverse_signal[i];
    // Finite and unsaturated, with a flat field (bitwise &: no branches).
    const bool good = !(value >= saturation) & (inverse > 0) & (value - value == 0);
    const float v = (value - dark[i]) * inverse;
    out[i - begin] = good ? v : NAN;
  }
}

// The maps of row y, band by band: xs = m0 x + row_x + m2 (row_x = m1 y), likewise ys, as
// register_pixel computes them (the same operations in the same order).
struct RowMaps {
  alignas(64) float m0[kMaxBands], m2[kMaxBands], m3[kMaxBands], m5[kMaxBands], row_x[kMaxBands], row_y[kMaxBands];

  RowMaps(const NativeFrames& f, int64_t y) {
    for (int64_t b = 0; b < f.bands; ++b) {
      const float* m = f.maps + 6 * b;
      m0[b] = m[0], m2[b] = m[2], m3[b] = m[3], m5[b] = m[5];
      row_x[b] = m[1] * static_cast<float>(y);
      row_y[b] = m[4] * static_cast<float>(y);
    }
  }
};

// Registered row y, out[x B + b], from the responses of native rows [row0, row1) (index ((r -
// row0) W + x) B + b), NaN where the pixel lies outside band b's frame or a tap is NaN. kBands:
// the band count when known at compile time (16, the instrument's: the band loop is one vector),
// 0 for any (B). Index: int32_t where the buffer's indices fit (32-bit gathers, twice the lanes of
// 64-bit ones), else int64_t.
template <int64_t kBands, typename Index>
SPHEREJAX_BANDS_CLONES void sample_row(const RowMaps& maps, const float* __restrict native, Index W, Index H,
                                       Index row0, Index row1, Index runtime_bands, float* __restrict out) {
  const Index B = kBands ? static_cast<Index>(kBands) : runtime_bands;
  const float last_x = static_cast<float>(W - 1), last_y = static_cast<float>(H - 1);
  const Index top_x = std::max<Index>(W - 2, 0), top_y = std::max<Index>(H - 2, 0);
  const Index first = row0, last = row1 - 1;
  for (Index x = 0; x < W; ++x) {
    const float fx_col = static_cast<float>(x);
    float* __restrict o = out + static_cast<int64_t>(x) * B;
    // Branch-free (selects, bitwise &), so that the compiler vectorises it over bands with gathers.
    for (Index b = 0; b < B; ++b) {
      float xs = maps.m0[b] * fx_col + maps.row_x[b] + maps.m2[b];
      float ys = maps.m3[b] * fx_col + maps.row_y[b] + maps.m5[b];
      const bool covered = (xs >= -kCoverageTolerance) & (xs <= last_x + kCoverageTolerance) &
                           (ys >= -kCoverageTolerance) & (ys <= last_y + kCoverageTolerance);
      xs = xs > 0.0f ? xs : 0.0f;
      xs = xs < last_x ? xs : last_x;
      ys = ys > 0.0f ? ys : 0.0f;
      ys = ys < last_y ? ys : last_y;
      Index x0 = static_cast<Index>(xs);
      x0 = x0 < top_x ? x0 : top_x;
      Index y0 = static_cast<Index>(ys);
      y0 = y0 < top_y ? y0 : top_y;
      const float fx = xs - static_cast<float>(x0), fy = ys - static_cast<float>(y0);
      const Index x1 = x0 + 1 < W ? x0 + 1 : W - 1;
      const Index y1 = y0 + 1 < H ? y0 + 1 : H - 1;
      // Rows within the buffer (its halo covers every row a map reaches; clamped all the same).
      Index r0 = y0 > first ? y0 : first;
      r0 = r0 < last ? r0 : last;
      Index r1 = y1 > first ? y1 : first;
      r1 = r1 < last ? r1 : last;
      const Index a = ((r0 - first) * W + x0) * B + b, a1 = ((r0 - first) * W + x1) * B + b;
      const Index c = ((r1 - first) * W + x0) * B + b, c1 = ((r1 - first) * W + x1) * B + b;
      const float sum = (1 - fy) * (1 - fx) * native[a] + (1 - fy) * fx * native[a1] + fy * (1 - fx) * native[c] +
                        fy * fx * native[c1];
      o[b] = covered ? sum : NAN;
    }
  }
}

#pragma GCC pop_options

#if defined(__x86_64__) && defined(__GNUC__)
// sample_row for 16 bands (the instrument's) and frames of at least 2 x 2 with AVX-512, one pixel's
// 16 bands a vector, without gathers: the taps of band b at pixel x lie at ((y0_b - row0) W + x0_b)
// 16 + b, and the bands whose (y0_b, x0_b) agree (a group: one to a few of them, as the maps
// displace the bands by different whole pixels) read their four taps by masked loads of the same
// four runs of 16 contiguous floats. The groups of a pixel are those of the pixel before it moved
// on by one, but where some band's whole-pixel offset changes (a few times a row): found again only
// then. The same operations on each lane as sample_row (max(x, 0) and min(x, last) give what its
// selects give, NaN included). Intrinsics, not GCC's vector extension: GCC 12 compiled the
// extension's comparisons and selects into scalar code (twice the correction's time), and its own
// gathers were slower on Zen 4 than the scalar loads it emits without them.
__attribute__((target("avx512f,avx512bw,avx512dq,avx512vl,fma")))
void sample_row_16_avx512(const RowMaps& maps, const float* __restrict native, int32_t W, int32_t H, int32_t row0,
                          int32_t row1, float* __restrict out, uint8_t* __restrict not_finite) {
  constexpr int32_t B = 16;
  const __m512 m0 = _mm512_load_ps(maps.m0), m2 = _mm512_load_ps(maps.m2), m3 = _mm512_load_ps(maps.m3);
  const __m512 m5 = _mm512_load_ps(maps.m5), row_x = _mm512_load_ps(maps.row_x), row_y = _mm512_load_ps(maps.row_y);
  const __m512 zero = _mm512_setzero_ps(), one = _mm512_set1_ps(1.0f), nan = _mm512_set1_ps(NAN);
  const __m512 last_x = _mm512_set1_ps(static_cast<float>(W - 1)), last_y = _mm512_set1_ps(static_cast<float>(H - 1));
  const __m512 low = _mm512_set1_ps(-kCoverageTolerance);
  const __m512 high_x = _mm512_set1_ps(static_cast<float>(W - 1) + kCoverageTolerance);
  const __m512 high_y = _mm512_set1_ps(static_cast<float>(H - 1) + kCoverageTolerance);
  const __m512i top_x = _mm512_set1_epi32(W - 2), top_y = _mm512_set1_epi32(H - 2);
  const __m512i first = _mm512_set1_epi32(row0), last = _mm512_set1_epi32(row1 - 2);
  const __m512i width = _mm512_set1_epi32(W), step = _mm512_set1_epi32(B);
  __mmask16 groups[B];
  int32_t group_offsets[B];
  int32_t count = 0;
  __m512i previous = _mm512_set1_epi32(-1);
  for (int32_t x = 0; x < W; ++x) {
    const __m512 column = _mm512_set1_ps(static_cast<float>(x));
    __m512 xs = _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(m0, column), row_x), m2);
    __m512 ys = _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(m3, column), row_y), m5);
    const __mmask16 covered = _mm512_cmp_ps_mask(xs, low, _CMP_GE_OQ) & _mm512_cmp_ps_mask(xs, high_x, _CMP_LE_OQ) &
                              _mm512_cmp_ps_mask(ys, low, _CMP_GE_OQ) & _mm512_cmp_ps_mask(ys, high_y, _CMP_LE_OQ);
    xs = _mm512_min_ps(_mm512_max_ps(xs, zero), last_x);
    ys = _mm512_min_ps(_mm512_max_ps(ys, zero), last_y);
    const __m512i x0 = _mm512_min_epi32(_mm512_cvttps_epi32(xs), top_x);
    const __m512i y0 = _mm512_min_epi32(_mm512_cvttps_epi32(ys), top_y);
    const __m512 fx = _mm512_sub_ps(xs, _mm512_cvtepi32_ps(x0)), fy = _mm512_sub_ps(ys, _mm512_cvtepi32_ps(y0));
    const __m512i r = _mm512_min_epi32(_mm512_max_epi32(y0, first), last);
    const __m512i offset = _mm512_slli_epi32(_mm512_add_epi32(_mm512_mullo_epi32(_mm512_sub_epi32(r, first), width), x0), 4);
    if (_mm512_cmpneq_epi32_mask(offset, _mm512_add_epi32(previous, step)) == 0) {
      for (int32_t g = 0; g < count; ++g) group_offsets[g] += B;
    } else {  // some band's whole-pixel offset changed: the groups again
      alignas(64) int32_t lanes[B];
      _mm512_store_si512(lanes, offset);
      __mmask16 todo = 0xffff;
      count = 0;
      while (todo) {
        const int32_t o = lanes[__builtin_ctz(todo)];
        const __mmask16 in_group = _mm512_cmpeq_epi32_mask(offset, _mm512_set1_epi32(o));
        todo &= static_cast<__mmask16>(~in_group);
        groups[count] = in_group;
        group_offsets[count++] = o;
      }
    }
    previous = offset;
    __m512 t00 = zero, t01 = zero, t10 = zero, t11 = zero;
    for (int32_t g = 0; g < count; ++g) {
      const float* tap = native + group_offsets[g];
      t00 = _mm512_mask_loadu_ps(t00, groups[g], tap);
      t01 = _mm512_mask_loadu_ps(t01, groups[g], tap + B);
      t10 = _mm512_mask_loadu_ps(t10, groups[g], tap + W * B);
      t11 = _mm512_mask_loadu_ps(t11, groups[g], tap + W * B + B);
    }
    const __m512 gx = _mm512_sub_ps(one, fx), gy = _mm512_sub_ps(one, fy);
    __m512 sum = _mm512_mul_ps(_mm512_mul_ps(gy, gx), t00);
    sum = _mm512_add_ps(sum, _mm512_mul_ps(_mm512_mul_ps(gy, fx), t01));
    sum = _mm512_add_ps(sum, _mm512_mul_ps(_mm512_mul_ps(fy, gx), t10));
    sum = _mm512_add_ps(sum, _mm512_mul_ps(_mm512_mul_ps(fy, fx), t11));
    const __m512 result = _mm512_mask_blend_ps(covered, nan, sum);
    _mm512_storeu_ps(out + static_cast<int64_t>(x) * B, result);
    not_finite[x] = _mm512_cmp_ps_mask(_mm512_sub_ps(result, result), zero, _CMP_EQ_OQ) != 0xffff;
  }
}

// sample_row_16_avx512 with AVX2 intrinsics, for CPUs without AVX-512 (most lab PCs): each half of
// the 16 bands (8 lanes) as sample_row_16_avx512 does all of them, with compare vectors for masks,
// movemask to find a half's groups, and blends of full loads for its taps.
__attribute__((target("avx2,fma")))
void sample_row_16_avx2(const RowMaps& maps, const float* __restrict native, int32_t W, int32_t H, int32_t row0,
                        int32_t row1, float* __restrict out, uint8_t* __restrict not_finite) {
  constexpr int32_t B = 16;
  const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f), nan = _mm256_set1_ps(NAN);
  const __m256 last_x = _mm256_set1_ps(static_cast<float>(W - 1)), last_y = _mm256_set1_ps(static_cast<float>(H - 1));
  const __m256 low = _mm256_set1_ps(-kCoverageTolerance);
  const __m256 high_x = _mm256_set1_ps(static_cast<float>(W - 1) + kCoverageTolerance);
  const __m256 high_y = _mm256_set1_ps(static_cast<float>(H - 1) + kCoverageTolerance);
  const __m256i top_x = _mm256_set1_epi32(W - 2), top_y = _mm256_set1_epi32(H - 2);
  const __m256i first = _mm256_set1_epi32(row0), last = _mm256_set1_epi32(row1 - 2);
  const __m256i width = _mm256_set1_epi32(W), step = _mm256_set1_epi32(B);
  for (int32_t x = 0; x < W; ++x) not_finite[x] = 0;
  for (int32_t half = 0; half < 2; ++half) {
    const int32_t lane0 = 8 * half;
    const __m256 m0 = _mm256_load_ps(maps.m0 + lane0), m2 = _mm256_load_ps(maps.m2 + lane0);
    const __m256 m3 = _mm256_load_ps(maps.m3 + lane0), m5 = _mm256_load_ps(maps.m5 + lane0);
    const __m256 row_x = _mm256_load_ps(maps.row_x + lane0), row_y = _mm256_load_ps(maps.row_y + lane0);
    __m256 groups[8];
    int32_t group_offsets[8];
    int32_t count = 0;
    __m256i previous = _mm256_set1_epi32(-1);
    for (int32_t x = 0; x < W; ++x) {
      const __m256 column = _mm256_set1_ps(static_cast<float>(x));
      __m256 xs = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(m0, column), row_x), m2);
      __m256 ys = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(m3, column), row_y), m5);
      const __m256 covered = _mm256_and_ps(
          _mm256_and_ps(_mm256_cmp_ps(xs, low, _CMP_GE_OQ), _mm256_cmp_ps(xs, high_x, _CMP_LE_OQ)),
          _mm256_and_ps(_mm256_cmp_ps(ys, low, _CMP_GE_OQ), _mm256_cmp_ps(ys, high_y, _CMP_LE_OQ)));
      xs = _mm256_min_ps(_mm256_max_ps(xs, zero), last_x);
      ys = _mm256_min_ps(_mm256_max_ps(ys, zero), last_y);
      const __m256i x0 = _mm256_min_epi32(_mm256_cvttps_epi32(xs), top_x);
      const __m256i y0 = _mm256_min_epi32(_mm256_cvttps_epi32(ys), top_y);
      const __m256 fx = _mm256_sub_ps(xs, _mm256_cvtepi32_ps(x0)), fy = _mm256_sub_ps(ys, _mm256_cvtepi32_ps(y0));
      const __m256i r = _mm256_min_epi32(_mm256_max_epi32(y0, first), last);
      const __m256i offset = _mm256_add_epi32(
          _mm256_slli_epi32(_mm256_add_epi32(_mm256_mullo_epi32(_mm256_sub_epi32(r, first), width), x0), 4),
          _mm256_set1_epi32(lane0));
      if (_mm256_movemask_epi8(_mm256_cmpeq_epi32(offset, _mm256_add_epi32(previous, step))) == -1) {
        for (int32_t g = 0; g < count; ++g) group_offsets[g] += B;
      } else {  // some band's whole-pixel offset changed: the groups again
        alignas(32) int32_t lanes[8];
        _mm256_store_si256(reinterpret_cast<__m256i*>(lanes), offset);
        int todo = 0xff;
        count = 0;
        while (todo) {
          const int32_t o = lanes[__builtin_ctz(todo)];
          const __m256 in_group = _mm256_castsi256_ps(_mm256_cmpeq_epi32(offset, _mm256_set1_epi32(o)));
          todo &= ~_mm256_movemask_ps(in_group);
          groups[count] = in_group;
          group_offsets[count++] = o;
        }
      }
      previous = offset;
      __m256 t00 = zero, t01 = zero, t10 = zero, t11 = zero;
      for (int32_t g = 0; g < count; ++g) {
        const float* tap = native + group_offsets[g];  // band lane0's value of the group's pixel
        t00 = _mm256_blendv_ps(t00, _mm256_loadu_ps(tap), groups[g]);
        t01 = _mm256_blendv_ps(t01, _mm256_loadu_ps(tap + B), groups[g]);
        t10 = _mm256_blendv_ps(t10, _mm256_loadu_ps(tap + W * B), groups[g]);
        t11 = _mm256_blendv_ps(t11, _mm256_loadu_ps(tap + W * B + B), groups[g]);
      }
      const __m256 gx = _mm256_sub_ps(one, fx), gy = _mm256_sub_ps(one, fy);
      __m256 sum = _mm256_mul_ps(_mm256_mul_ps(gy, gx), t00);
      sum = _mm256_add_ps(sum, _mm256_mul_ps(_mm256_mul_ps(gy, fx), t01));
      sum = _mm256_add_ps(sum, _mm256_mul_ps(_mm256_mul_ps(fy, gx), t10));
      sum = _mm256_add_ps(sum, _mm256_mul_ps(_mm256_mul_ps(fy, fx), t11));
      const __m256 result = _mm256_blendv_ps(nan, sum, covered);
      _mm256_storeu_ps(out + static_cast<int64_t>(x) * B + lane0, result);
      not_finite[x] |= _mm256_movemask_ps(_mm256_cmp_ps(_mm256_sub_ps(result, result), zero, _CMP_EQ_OQ)) != 0xff;
    }
  }
}

#endif

template <typename Index>
void sample_rows_as(const RowMaps& maps, const float* native, const NativeFrames& f, int64_t row0, int64_t row1,
                    float* out) {
  const Index W = static_cast<Index>(f.width), H = static_cast<Index>(f.height), B = static_cast<Index>(f.bands);
  if (B == 16) {
    sample_row<16, Index>(maps, native, W, H, static_cast<Index>(row0), static_cast<Index>(row1), B, out);
  } else {
    sample_row<0, Index>(maps, native, W, H, static_cast<Index>(row0), static_cast<Index>(row1), B, out);
  }
}

// bits[x] on entry: 1 where pixel x of the sampled row has a value that is not finite (or may
// have: the sampler's flags), else 0. Those pixels are done again exactly.
template <typename Raw>
void exact_pixels(const NativeFrames& f, int64_t image, int64_t y, float placeholder, float* out, uint8_t* bits) {
  const int64_t W = f.width, B = f.bands;
  const Raw* raw = static_cast<const Raw*>(f.raw) + image * f.height * W * B;
  for (int64_t x = 0; x < W; ++x) {
    float* values = out + x * B;
    if (!bits[x]) continue;
    bits[x] = register_pixel<Raw>(f, raw, y, x, values);
    if (bits[x]) std::fill(values, values + B, placeholder);
  }
}

}  // namespace

void native_responses(const NativeFrames& f, int64_t image, int64_t row0, int64_t row1, float* out) {
  const int64_t row = f.width * f.bands, offset = image * f.height * row;
  const int64_t begin = row0 * row, end = row1 * row;
  if (f.u16) {
    responses<uint16_t>(static_cast<const uint16_t*>(f.raw) + offset, f.dark, f.inverse_signal, f.saturation, begin,
                        end, out);
  } else {
    responses<float>(static_cast<const float*>(f.raw) + offset, f.dark, f.inverse_signal, f.saturation, begin, end,
                     out);
  }
}

void registered_row(const NativeFrames& f, int64_t image, const float* native, int64_t row0, int64_t row1, int64_t y,
                    float placeholder, float* out, uint8_t* bits) {
  const RowMaps maps(f, y);
  bool sampled = false;  // true once bits holds the sampler's not-finite flags
  const bool fits = (row1 - row0) * f.width * f.bands < (int64_t(1) << 31);
  const bool vector_of_bands = fits && f.bands == 16 && f.width >= 2 && f.height >= 2 && row1 - row0 >= 2;
  const int32_t W = static_cast<int32_t>(f.width), H = static_cast<int32_t>(f.height);
#if defined(__x86_64__) && defined(__GNUC__)
  if (vector_of_bands && f.avx512) {
    sample_row_16_avx512(maps, native, W, H, static_cast<int32_t>(row0), static_cast<int32_t>(row1), out, bits);
    sampled = true;
  } else if (vector_of_bands && f.avx2) {
    sample_row_16_avx2(maps, native, W, H, static_cast<int32_t>(row0), static_cast<int32_t>(row1), out, bits);
    sampled = true;
  }
#endif
  if (!sampled && fits) {
    sample_rows_as<int32_t>(maps, native, f, row0, row1, out);
  } else if (!sampled) {
    sample_rows_as<int64_t>(maps, native, f, row0, row1, out);
  }
  if (!sampled) {
    const int64_t W = f.width, B = f.bands;
    for (int64_t x = 0; x < W; ++x) {
      bool finite = true;
      for (int64_t b = 0; b < B; ++b) finite &= out[x * B + b] - out[x * B + b] == 0;
      bits[x] = !finite;
    }
  }
  if (f.u16) {
    exact_pixels<uint16_t>(f, image, y, placeholder, out, bits);
  } else {
    exact_pixels<float>(f, image, y, placeholder, out, bits);
  }
}

}  // namespace spherejax_bands
