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
// It computes what the jax.numpy definition computes (band_taps.h gives the equations), in
// float32, value by value, and u' = (bits == 0 ? v' : -1) * registered_signal per pixel.
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
#include <vector>

#include "band_taps.h"
#include "call.h"
#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace spherejax_register {
namespace {

using spherejax_bands::NativeFrames;
constexpr int64_t kRowsPerChunk = 16;

struct Registration {
  NativeFrames native;
  int64_t images = 0;
  const float* registered_signal = nullptr;
  float* frames = nullptr;
  uint8_t* bits = nullptr;
};

// Output rows [first, last) of the images (row index = image * H + y, within one image): the
// native responses of the rows they need (band_taps.h, native_responses), each row registered
// (registered_row, flagged pixels -1), then written out times s'.
void register_rows(const Registration& r, int64_t first, int64_t last, int64_t halo, std::vector<float>& work) {
  const NativeFrames& f = r.native;
  const int64_t H = f.height, W = f.width, B = f.bands;
  const int64_t image = first / H, y_first = first % H, y_last = (last - 1) % H + 1;
  const int64_t row0 = std::max<int64_t>(y_first - halo, 0), row1 = std::min<int64_t>(y_last + halo, H);
  work.resize(size_t((row1 - row0) * W * B + W * B));
  float* native = work.data();
  float* row = native + (row1 - row0) * W * B;
  spherejax_bands::native_responses(f, image, row0, row1, native);
  for (int64_t y = y_first; y < y_last; ++y) {
    float* out = r.frames + ((image * H + y) * W) * B;
    uint8_t* bits = r.bits + (image * H + y) * W;
    spherejax_bands::registered_row(f, image, native, row0, row1, y, -1.0f, row, bits);
    const float* s = r.registered_signal + y * W * B;
    for (int64_t i = 0; i < W * B; ++i) out[i] = row[i] * s[i];
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
    std::vector<float> buffer;  // this thread's native responses, reused chunk after chunk
    const int64_t H = problem.native.height;
    for (int64_t chunk; (chunk = next.fetch_add(1)) < chunks;) {
      // Chunks never straddle two images.
      const int64_t image = chunk / chunks_per_image, k = chunk % chunks_per_image;
      const int64_t first = image * H + k * kRowsPerChunk, last = image * H + std::min(H, (k + 1) * kRowsPerChunk);
      register_rows(problem, first, last, halo, buffer);
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
  Registration& reg = shared->problem;
  NativeFrames& r = reg.native;
  reg.images = dims[0], r.height = dims[1], r.width = dims[2], r.bands = dims[3];
  const size_t frame = size_t(r.height * r.width * r.bands);
  if (r.bands < 1 || r.bands > spherejax_bands::kMaxBands) return ffi::Error::InvalidArgument("bands: expected 1..256");
  if (dark.element_count() != frame || inverse_signal.element_count() != frame ||
      registered_signal.element_count() != frame || maps.element_count() != size_t(r.bands * 6)) {
    return ffi::Error::InvalidArgument("inputs: shapes do not match raw (N, H, W, B)");
  }
  r.raw = raw.untyped_data();
  r.u16 = u16;
  r.dark = dark.typed_data();
  r.inverse_signal = inverse_signal.typed_data();
  r.maps = maps.typed_data();
  r.saturation = saturation;
  r.avx512 = spherejax_fused::variant_supported(static_cast<int32_t>(spherejax_fused::Variant::kAvx512));
  r.avx2 = spherejax_fused::variant_supported(static_cast<int32_t>(spherejax_fused::Variant::kAvx2));
  reg.registered_signal = registered_signal.typed_data();
  reg.frames = frames->typed_data();
  reg.bits = bits->typed_data();
  shared->chunks_per_image = (r.height + kRowsPerChunk - 1) / kRowsPerChunk;
  shared->chunks = reg.images * shared->chunks_per_image;
  shared->halo = spherejax_bands::halo_rows(r);
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
