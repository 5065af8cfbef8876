// One call of the kernel (call.h): the variants and their dispatch, the Problem of a call, and
// the chunks shared out to threads.

#include "call.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <mutex>
#include <new>
#include <vector>

namespace spherejax_fused {

const char* variant_name(int32_t code) {
  switch (static_cast<Variant>(code)) {
    case Variant::kAvx512: return "avx512";
    case Variant::kAvx2: return "avx2";
    case Variant::kGeneric: return "generic";
    default: return nullptr;
  }
}

bool variant_supported(int32_t code) {
#if SPHEREJAX_X86
  // The instructions of SPHEREJAX_AVX512_TARGET and SPHEREJAX_AVX2_TARGET (fused_correct.h).
  static const bool avx512 = __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512bw") &&
                             __builtin_cpu_supports("avx512dq") && __builtin_cpu_supports("avx512vl") &&
                             __builtin_cpu_supports("fma");
  static const bool avx2 = __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma");
#else
  constexpr bool avx512 = false, avx2 = false;
#endif
  switch (static_cast<Variant>(code)) {
    case Variant::kAvx512: return avx512;
    case Variant::kAvx2: return avx2;
    case Variant::kGeneric: return true;
    default: return false;
  }
}

Variant resolve_variant(int32_t requested, const char** error) {
  *error = nullptr;
  if (static_cast<Variant>(requested) == Variant::kBest) {
    for (Variant widest : {Variant::kAvx512, Variant::kAvx2}) {
      if (variant_supported(static_cast<int32_t>(widest))) return widest;
    }
    return Variant::kGeneric;
  }
  if (variant_name(requested) == nullptr) {
    *error = "variant: expected 0 (the widest this CPU runs), 1 (avx512), 2 (avx2) or 3 (generic)";
  } else if (!variant_supported(requested)) {
    *error = "variant: this CPU does not run that variant's instructions (see supported_variants())";
  }
  return static_cast<Variant>(requested);
}

void correct_range(const Problem& pr, int64_t first, int64_t last) {
#if SPHEREJAX_X86
  // The variants' own code is for 16 bands only; resolve_variant has checked the CPU runs it.
  if (pr.bands == kLanes && pr.variant == Variant::kAvx512) return correct_range_avx512(pr, first, last);
  if (pr.bands == kLanes && pr.variant == Variant::kAvx2) return correct_range_avx2(pr, first, last);
#endif
  correct_range_generic(pr, first, last);
}

void Shared::chunk_done() {
  if (finished.fetch_add(1) + 1 == chunks) {
    std::lock_guard<std::mutex> lock(mutex);
    all_done.notify_all();
  }
}

void Shared::work() {
  if (registered) return work_registered();
  const int64_t total = problem.images * problem.pixels;
  for (int64_t chunk; (chunk = next.fetch_add(1)) < chunks;) {
    const int64_t first = chunk * kChunk, last = std::min(total, first + kChunk);
    correct_range(problem, first, last);
    chunk_done();
  }
}

namespace {

// Scratch memory kept from call to call: a call's threads are new ones on the direct route
// (module.cc), and fresh pages of a few megabytes a thread cost the kernel a fifth of its time
// zeroing them (perf: clear_page). A buffer is taken whole by one thread and given back after.
struct Scratch {
  std::vector<float> responses, row;
  std::vector<uint8_t> bits;
};

std::mutex scratch_mutex;
std::vector<std::unique_ptr<Scratch>> scratch_kept;

std::unique_ptr<Scratch> take_scratch() {
  std::lock_guard<std::mutex> lock(scratch_mutex);
  if (scratch_kept.empty()) return std::make_unique<Scratch>();
  std::unique_ptr<Scratch> scratch = std::move(scratch_kept.back());
  scratch_kept.pop_back();
  return scratch;
}

void give_scratch(std::unique_ptr<Scratch> scratch) {
  std::lock_guard<std::mutex> lock(scratch_mutex);
  if (scratch_kept.size() < 64) scratch_kept.push_back(std::move(scratch));
}

}  // namespace

void Shared::work_registered() {
  const int64_t H = native.height, W = native.width, B = native.bands;
  // This thread's buffers, reused chunk after chunk: the native responses of a chunk's rows and
  // their halo, and one registered row with its bits (W B floats: in L2 when the kernel reads it).
  std::unique_ptr<Scratch> scratch = take_scratch();
  std::vector<float>& responses = scratch->responses;
  std::vector<float>& row = scratch->row;
  std::vector<uint8_t>& bits = scratch->bits;
  row.resize(static_cast<size_t>(W * B));
  bits.resize(static_cast<size_t>(W));
  constexpr uint8_t kPlaceholderBit = 16;  // BELOW_DARK, what the -1 of a flagged pixel sets
  for (int64_t chunk; (chunk = next.fetch_add(1)) < chunks;) {
    const int64_t image = chunk / chunks_per_image, k = chunk % chunks_per_image;
    const int64_t y_first = k * rows_per_chunk, y_last = std::min(H, y_first + rows_per_chunk);
    const int64_t row0 = std::max<int64_t>(y_first - halo, 0), row1 = std::min<int64_t>(y_last + halo, H);
    responses.resize(size_t((row1 - row0) * W * B));
    spherejax_bands::native_responses(native, image, row0, row1, responses.data());
    for (int64_t y = y_first; y < y_last; ++y) {
      spherejax_bands::registered_row(native, image, responses.data(), row0, row1, y, -1.0f, row.data(), bits.data());
      Problem local = problem;
      const int64_t first = (image * H + y) * W;
      local.raw = row.data();
      local.raw_is_u16 = false;
      local.raw_first = first;
      correct_range(local, first, first + W);
      for (int64_t x = 0; x < W; ++x) {
        if (bits[x] == 0) continue;
        uint8_t& q = problem.quality[first + x];
        q = static_cast<uint8_t>((q & ~kPlaceholderBit) | bits[x]);
      }
    }
    chunk_done();
  }
  give_scratch(std::move(scratch));
}

void register_bands_first(Prepared& prepared, const spherejax_bands::NativeFrames& native) {
  Shared& shared = *prepared.shared;
  Problem& pr = shared.problem;
  const int64_t B = pr.bands;
  prepared.unit_dark = std::make_unique<float[]>(B);  // zeros
  prepared.unit_white = std::make_unique<float[]>(B);
  std::fill(prepared.unit_white.get(), prepared.unit_white.get() + B, 1.0f);
  pr.dark = prepared.unit_dark.get();
  pr.white = prepared.unit_white.get();
  pr.calibration_stride = 0;
  pr.saturation = NAN;
  shared.registered = true;
  shared.native = native;
  // The variant resolve_variant checked against the CPU, and AVX2 under AVX-512's.
  shared.native.avx512 = pr.variant == Variant::kAvx512;
  shared.native.avx2 = pr.variant != Variant::kGeneric && variant_supported(static_cast<int32_t>(Variant::kAvx2));
  shared.halo = spherejax_bands::halo_rows(native);
  // 32 rows a chunk: the halo's rows (2-4 beyond each side for maps of a few pixels) computed twice
  // cost an eighth to a quarter more native responses; more rows would cost cache.
  shared.rows_per_chunk = 32;
  shared.chunks_per_image = (native.height + shared.rows_per_chunk - 1) / shared.rows_per_chunk;
  shared.chunks = pr.images * shared.chunks_per_image;
}

namespace {

// `count` vectors on a 64-byte boundary, which the aligned loads of the projection rows need.
// (Not std::unique_ptr<Vec[]> members: GCC warns that a template argument drops Vec's alignment
// attribute; an explicit aligned_alloc does not depend on what the compiler keeps of it.)
std::unique_ptr<float[], FreeAligned> aligned_vectors(int64_t count) {
  return std::unique_ptr<float[], FreeAligned>(
      static_cast<float*>(std::aligned_alloc(64, std::max<int64_t>(count, 1) * sizeof(Vec))));
}

}  // namespace

const char* check_residual(const Residual& r) {
  if (r.whitened_rows < 0 || r.whitened_rows % kResidualRows != 0 || r.inducing_rows < 0 ||
      r.inducing_rows % kResidualRows != 0) {
    return "residual: expected whitening and inducing rows in eights";
  }
  if (r.inducing_rows > 0 && r.whitened_rows == 0) return "residual: inducing points without a whitening";
  return nullptr;
}

std::unique_ptr<Prepared> prepare(const void* raw, bool u16, const float* dark, const float* white,
                                  const float* ratio, const float* c, const float* m,
                                  const float* offsets, const float* wxyz, int64_t images, int64_t pixels,
                                  int64_t bands, float saturation, Variant variant, const Residual& residual,
                                  float* reflectance, float* lab, uint8_t* quality) {
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
  int64_t rank = 0;
  if (residual.inducing_rows > 0) {
    prepared->basis = aligned_vectors(3 * kResidualRank);
    // The whitening and inducing rows in base 2 (Problem): u scaled by sqrt(log2 e) makes |u|^2 / 2
    // log2 e times itself, and the inducing rows by log2 e the rest of each exponent.
    const int64_t width = bands + 1;
    const int64_t whitening_floats = residual.whitened_rows * width, inducing_floats = residual.inducing_rows * width;
    prepared->whitening = aligned_vectors((whitening_floats + kLanes - 1) / kLanes);
    prepared->inducing = aligned_vectors((inducing_floats + kLanes - 1) / kLanes);
    if (!prepared->basis || !prepared->whitening || !prepared->inducing) throw std::bad_alloc();
    constexpr double kLog2e = 1.4426950408889634;
    const float root_log2e = static_cast<float>(std::sqrt(kLog2e));
    for (int64_t i = 0; i < whitening_floats; ++i) prepared->whitening[i] = residual.whitening[i] * root_log2e;
    for (int64_t i = 0; i < inducing_floats; ++i) {
      prepared->inducing[i] = static_cast<float>(residual.inducing[i] * kLog2e);
    }
    for (int64_t r = 0; r < kResidualRank; ++r) {
      float* row = prepared->basis.get() + 3 * kLanes * r;
      for (int64_t k = 0; k < kPadded; ++k) row[k] = k < kOutputs ? residual.basis[r * kOutputs + k] : 0.0f;
    }
    // The ranks in use: the last column of G (factor) with a value that is not zero. The caller
    // zeroes the components its weights do not have (fused_constants.residual_constants), and a
    // residual of rank 4 or less then runs the half-rank code (residual_of<..., 4>).
    for (int64_t j = 0; j < residual.inducing_rows; ++j) {
      for (int64_t r = rank; r < kResidualRank; ++r) {
        if (residual.factor[j * kResidualRank + r] != 0.0f) rank = r + 1;
      }
    }
  }

  Problem& pr = prepared->shared->problem;
  pr.raw = raw;
  pr.raw_is_u16 = u16;
  pr.raw_first = 0;
  pr.dark = dark;
  pr.white = white;
  pr.calibration_stride = bands;
  pr.images = images;
  pr.pixels = pixels;
  pr.bands = bands;
  pr.saturation = saturation;
  pr.variant = variant;
  pr.gain = gain;
  pr.offset = offset;
  pr.image_bad = prepared->image_bad.get();
  pr.projection = reinterpret_cast<const Vec*>(prepared->padded.get());
  pr.bias = reinterpret_cast<const Vec*>(prepared->padded_bias.get());
  for (int k = 0; k < 3; ++k) pr.inverse_white[k] = 1.0f / wxyz[k];
  pr.whitened_rows = residual.inducing_rows > 0 ? residual.whitened_rows : 0;
  pr.inducing_rows = residual.inducing_rows;
  pr.residual_rank = rank <= kResidualRank / 2 ? kResidualRank / 2 : kResidualRank;
  pr.whitening = prepared->whitening.get();
  pr.inducing = prepared->inducing.get();
  pr.factor = residual.factor;
  pr.basis = reinterpret_cast<const Vec*>(prepared->basis.get());
  pr.reflectance = reflectance;
  pr.lab = lab;
  pr.quality = quality;
  prepared->shared->chunks = (images * pixels + kChunk - 1) / kChunk;
  return prepared;
}

}  // namespace spherejax_fused
