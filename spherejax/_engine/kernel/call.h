// One call of the kernel, whichever entry made it (ffi_handler.cc: XLA; module.cc: CPython): the
// variant it asked for, checked against the CPU; its Problem and the per-image constants the
// Problem points to; and the chunks of pixels shared out to threads. Implemented in call.cc.

#ifndef SPHEREJAX_FUSED_CALL_H_
#define SPHEREJAX_FUSED_CALL_H_

#include <atomic>
#include <condition_variable>
#include <cstdint>
#include <cstdlib>
#include <memory>
#include <mutex>

#include "band_taps.h"
#include "fused_correct.h"

namespace spherejax_fused {

// The name of a variant ("avx512", "avx2", "generic"; spherejax._engine.fused uses the same), or
// nullptr for a code that is no variant (kBest included).
const char* variant_name(int32_t code);

// True if this build has the variant's code and this CPU runs it (the instructions its target
// attributes name, as __builtin_cpu_supports reports them). kBest: false (it is no variant).
bool variant_supported(int32_t code);

// The variant a call that asked for `requested` runs: kBest becomes the widest the CPU runs,
// AVX-512, then AVX2, then generic (what the kernel did before spherejax._engine.fused measured
// which is fastest); an explicit variant is itself. nullptr in *error where that is a variant;
// otherwise a message, and the call must be refused: an unknown code, or one the CPU does not run
// (it would die of an illegal instruction).
Variant resolve_variant(int32_t requested, const char** error);

// Runs the pixels [first, last) of pr with pr.variant's code (16 bands; the generic code for any
// other band count).
void correct_range(const Problem& pr, int64_t first, int64_t last);

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

  // A call with band maps (register_bands_first): the native frames, and chunks of rows_per_chunk
  // rows of one image, each registered row by row into a buffer of its thread's and corrected
  // from there (work_registered).
  bool registered = false;
  spherejax_bands::NativeFrames native;
  int64_t halo = 0, rows_per_chunk = 0, chunks_per_image = 0;

  void work();

 private:
  void work_registered();
  void chunk_done();
};

// One call's Problem and the arrays it points to besides the caller's: the per-image gains,
// offsets and flags, and the projection and bias padded to whole vectors. Layouts as in the
// header of fused_correct.h.
struct FreeAligned {
  void operator()(float* p) const { std::free(p); }
};

struct Prepared {
  std::shared_ptr<Shared> shared = std::make_shared<Shared>();
  std::unique_ptr<float[]> gain, offset;
  std::unique_ptr<uint8_t[]> image_bad;
  std::unique_ptr<float[], FreeAligned> padded, padded_bias;
  std::unique_ptr<float[], FreeAligned> basis;  // the kernel residual's, padded to whole vectors
  std::unique_ptr<float[], FreeAligned> whitening, inducing;  // the kernel residual's, in base 2 (Problem)
  std::unique_ptr<float[]> unit_dark, unit_white;  // a call with band maps: 0 and 1 in every band
};

// The kernel residual of a call (fused_correct.h, residual_of), as its caller passes it:
// whitening (D, B + 1), inducing (M, B + 1), factor (M, kResidualRank) and basis (kResidualRank,
// kOutputs), row-major floats; D and M multiples of 8, M = 0 for a call without one.
struct Residual {
  const float* whitening = nullptr;
  const float* inducing = nullptr;
  const float* factor = nullptr;
  const float* basis = nullptr;
  int64_t whitened_rows = 0, inducing_rows = 0;  // D, M
};

// nullptr if `r` is a residual the kernel takes (or none); else why not.
const char* check_residual(const Residual& r);

// The Problem of one call and what it points to. `variant`: a resolved one (resolve_variant).
// Throws std::bad_alloc when memory runs out.
std::unique_ptr<Prepared> prepare(const void* raw, bool u16, const float* dark, const float* white,
                                  const float* ratio, const float* c, const float* m,
                                  const float* offsets, const float* wxyz, int64_t images, int64_t pixels,
                                  int64_t bands, float saturation, Variant variant, const Residual& residual,
                                  float* reflectance, float* lab, uint8_t* quality);

// Makes a prepared call (prepare, with raw, dark and saturation those of the native frames
// `native`; white unused) one of a calibration with band maps: every row is first registered into
// the reference band's geometry (band_taps.h: v' and its bits, flagged pixels -1 in every band), then
// corrected as v' (dark 0, white 1, no saturation level: the registration flagged saturated taps)
// with the registration's bits in its quality (where it flagged a pixel, they replace the BELOW_DARK
// that the -1 made, as spherejax.band_resampling.merged_quality does). The same outputs as the
// registered frames u' = v' s' corrected with dark 0 and white s', to float rounding, without the
// registered frames written or read back. pixels must be native.height * native.width.
void register_bands_first(Prepared& prepared, const spherejax_bands::NativeFrames& native);

// Runs the chunks on the calling thread and whatever helpers `schedule` started, then waits for
// the last chunk.
template <typename Schedule>
void run(Shared& shared, Schedule schedule) {
  schedule();
  shared.work();
  std::unique_lock<std::mutex> lock(shared.mutex);
  shared.all_done.wait(lock, [&] { return shared.finished.load() == shared.chunks; });
}

}  // namespace spherejax_fused

#endif  // SPHEREJAX_FUSED_CALL_H_
