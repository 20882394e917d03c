// Small pieces shared by the readers and writers: the GLB container and
// welding vertices by exact position.
#pragma once

#include <array>
#include <cstdint>
#include <cstring>
#include <string>
#include <unordered_map>
#include <vector>

namespace iteas {

// A GLB file: header, JSON chunk (space-padded) and, when |bin| is given, a BIN
// chunk (zero-padded). Empty when the file would pass the 4 GiB its 32-bit
// length field can hold (a GLB is never empty).
std::vector<uint8_t> pack_glb(const std::string& json, const uint8_t* bin, size_t bin_size);

// Maps bit-identical positions (with -0 equal to +0) to one vertex index.
class Welder {
 public:
  // Returns the vertex for |p| and whether it is new.
  std::pair<int32_t, bool> weld(const float p[3], int32_t next_index) {
    Key key;
    for (int k = 0; k < 3; ++k) {
      const float x = p[k] == 0.0f ? 0.0f : p[k];
      std::memcpy(&key.b[k], &x, 4);
    }
    auto [it, inserted] = map_.emplace(key, next_index);
    return {it->second, inserted};
  }

 private:
  struct Key {
    std::array<uint32_t, 3> b;
    bool operator==(const Key& o) const { return b == o.b; }
  };
  struct Hash {
    size_t operator()(const Key& k) const {
      return (size_t(k.b[0]) * 73856093u) ^ (size_t(k.b[1]) * 19349663u) ^ (size_t(k.b[2]) * 83492791u);
    }
  };
  std::unordered_map<Key, int32_t, Hash> map_;
};

}  // namespace iteas
