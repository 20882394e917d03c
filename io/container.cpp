#include "io/container.h"

namespace iteas {

std::vector<uint8_t> pack_glb(const std::string& json, const uint8_t* bin, size_t bin_size) {
  // Sizes in 64 bits first: the header's fields are 32-bit.
  const uint64_t padded_json = (uint64_t(json.size()) + 3) & ~uint64_t(3);
  const uint64_t padded_bin = (uint64_t(bin_size) + 3) & ~uint64_t(3);
  if (12 + 8 + padded_json + (bin ? 8 + padded_bin : 0) > UINT32_MAX) return {};
  const uint32_t json_len = uint32_t(padded_json), bin_len = uint32_t(padded_bin);
  const uint32_t total = 12 + 8 + json_len + (bin ? 8 + bin_len : 0);
  std::vector<uint8_t> out(total, 0);
  auto put = [&](size_t at, uint32_t v) { std::memcpy(out.data() + at, &v, 4); };
  put(0, 0x46546C67);  // "glTF"
  put(4, 2);
  put(8, total);
  put(12, json_len);
  put(16, 0x4E4F534A);  // "JSON"
  std::memcpy(out.data() + 20, json.data(), json.size());
  for (size_t i = json.size(); i < json_len; ++i) out[20 + i] = ' ';
  if (bin) {
    put(20 + json_len, bin_len);
    put(24 + json_len, 0x004E4942);  // "BIN"
    if (bin_size) std::memcpy(out.data() + 28 + json_len, bin, bin_size);
  }
  return out;
}

}  // namespace iteas
