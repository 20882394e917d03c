// Readers and writers on real files, broken files, truncated and corrupted
// bytes (issue 2, points 2-3). Run under the Asan build too.
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <memory>
#include <random>
#include <thread>
#include <unistd.h>
#include <set>

#include "io/container.h"
#include "io/draco_codec.h"
#include "io/memory_budget.h"
#include "io/pipeline.h"
#include "tests/support.h"

namespace iteas {
namespace {

std::set<std::string> attribute_set(const Document& d) {
  std::set<std::string> s;
  for (const MeshSlot& slot : d.meshes)
    for (const Channel& ch : slot.mesh.channels) s.insert(ch.name);
  return s;
}

int64_t triangles(const Document& d) {
  int64_t n = 0;
  for (const MeshSlot& s : d.meshes) n += s.mesh.num_faces();
  return n;
}

TEST(Io, EveryValidMeshRoundTripsThroughGlb) {
  int converted = 0;
  for (const std::string& path : test::valid_mesh_files()) {
    SCOPED_TRACE(path);
    Document in;
    const Status s = test::load(path, &in);
    if (!s.ok()) {
      // Only point clouds (no triangles) may fail, with the documented code.
      EXPECT_EQ(s.kind, ErrorKind::kUnusable) << s.message;
      EXPECT_EQ(s.code, "no_triangles");
      continue;
    }
    for (bool draco : {false, true}) {
      OutputOptions opt;
      opt.draco = draco;
      std::vector<uint8_t> bytes;
      WriteCounts counts;
      ASSERT_TRUE(write_document(in, opt, "glb", nullptr, &bytes, &counts).ok());
      Document out;
      const Status r = read_document(bytes.data(), bytes.size(), "glb", ReadLimits(), &out);
      ASSERT_TRUE(r.ok()) << r.message;
      // Draco may drop triangles that quantization collapses (counted by the
      // writer) or keep them with two equal points (dropped, and counted, on reading).
      int64_t dropped = 0;
      for (const MeshSlot& s : out.meshes) dropped += s.dropped_faces;
      EXPECT_EQ(triangles(out) + dropped, counts.triangles);
      if (!draco) { EXPECT_EQ(dropped, 0); }
      EXPECT_EQ(counts.triangles + counts.quantization_collapsed, triangles(in));
      if (!draco) { EXPECT_EQ(counts.quantization_collapsed, 0); }
      EXPECT_EQ(attribute_set(out), attribute_set(in));
      EXPECT_EQ(out.meshes.size(), in.meshes.size());
    }
    ++converted;
  }
  EXPECT_GT(converted, 20);
}

TEST(Io, NastyFilesFailCleanlyOrWarn) {
  for (const std::string& path : test::nasty_files()) {
    SCOPED_TRACE(path);
    const std::vector<uint8_t> b = test::read_bytes(path);
    JobRequest rq;
    rq.data = b.data();
    rq.size = b.size();
    rq.name_hint = path;
    rq.output_format = "glb";
    rq.options.refine.levels = 2;
    JobResult res;
    const Status s = run_job(rq, JobHooks(), &res);
    if (!s.ok()) {
      EXPECT_FALSE(s.message.empty());
      EXPECT_EQ(s.message.find('\n'), std::string::npos);
      EXPECT_NE(s.kind, ErrorKind::kIo);
    } else {
      EXPECT_FALSE(res.bytes.empty());
      EXPECT_TRUE(res.stats.contains("warnings"));
    }
  }
}

// Found by fuzz/fuzz_read: a morph target's POSITION as VEC2 with the right
// count passed the count check, then was read three floats per vertex.
TEST(Io, MorphTargetPositionsMustBeVec3) {
  const std::vector<uint8_t> b = test::read_bytes(test::data_dir() + "/nasty/morph_target_position_vec2.glb");
  ASSERT_FALSE(b.empty());
  Document d;
  const Status s = read_document(b.data(), b.size(), "glb", ReadLimits(), &d);
  EXPECT_FALSE(s.ok());
  EXPECT_EQ(s.code, "bad_accessor") << s.message;
}

void expect_no_crash_on_prefixes(const std::string& path, size_t step) {
  const std::vector<uint8_t> b = test::read_bytes(path);
  ASSERT_FALSE(b.empty()) << path;
  const std::string fmt = sniff_format(b.data(), b.size(), path);
  for (size_t n = 0; n < b.size(); n += step) {
    std::vector<uint8_t> prefix(b.begin(), b.begin() + n);  // exact-size copy so ASan sees overreads
    Document d;
    const Status s = read_document(prefix.data(), prefix.size(), fmt, ReadLimits(), &d);
    if (!s.ok()) { EXPECT_FALSE(s.message.empty()); }
  }
}

TEST(Io, TruncatedGlbPrefixesAreRejectedCleanly) { expect_no_crash_on_prefixes(test::data_dir() + "/Box.glb", 1); }
TEST(Io, TruncatedDracoGlbPrefixesAreRejectedCleanly) { expect_no_crash_on_prefixes(test::data_dir() + "/Box_Draco.glb", 1); }
TEST(Io, TruncatedDrcPrefixesAreRejectedCleanly) {
  expect_no_crash_on_prefixes(test::data_dir() + "/cube_att.drc", 1);
  expect_no_crash_on_prefixes(test::data_dir() + "/eight.drc", 1);
}

TEST(Io, BitFlippedInputsDoNotCrash) {
  std::mt19937 rng(12345);
  for (const char* name : {"Box.glb", "Box_Draco.glb", "cube_att.drc", "eight.off", "Box.gltf"}) {
    const std::vector<uint8_t> b = test::read_bytes(test::data_dir() + "/" + name);
    for (int i = 0; i < 300; ++i) {
      std::vector<uint8_t> x = b;
      for (int k = 0; k < 4; ++k) x[rng() % x.size()] ^= uint8_t(1u << (rng() % 8));
      Document d;
      read_document(x.data(), x.size(), sniff_format(x.data(), x.size(), name), ReadLimits(), &d);
    }
  }
}

TEST(Io, ExternalUrisAreRefusedWithoutOpeningAnything) {
  for (const char* uri : {"file:///etc/passwd", "../secret.bin", "http://127.0.0.1:1/x.bin", "/etc/passwd"}) {
    const std::string json = std::string(R"({"asset":{"version":"2.0"},"buffers":[{"uri":")") + uri +
                             R"(","byteLength":36}],"bufferViews":[{"buffer":0,"byteLength":36}],)"
                             R"("accessors":[{"bufferView":0,"componentType":5126,"count":3,"type":"VEC3","min":[0,0,0],"max":[1,1,0]}],)"
                             R"("meshes":[{"primitives":[{"attributes":{"POSITION":0}}]}]})";
    Document d;
    const Status s = read_document(reinterpret_cast<const uint8_t*>(json.data()), json.size(), "gltf", ReadLimits(), &d);
    EXPECT_EQ(s.code, "external_uri") << uri;
    EXPECT_EQ(s.kind, ErrorKind::kBadInput);
  }
}

TEST(Io, AbsurdDeclaredCountsAreRefusedBeforeAllocating) {
  // A sparse accessor without a bufferView may declare any count: the limit holds.
  const std::string json =
      R"({"asset":{"version":"2.0"},"accessors":[{"componentType":5126,"count":2147483647,"type":"VEC3",)"
      R"("min":[0,0,0],"max":[1,1,1]}],"meshes":[{"primitives":[{"attributes":{"POSITION":0}}]}]})";
  Document d;
  const Status s = read_document(reinterpret_cast<const uint8_t*>(json.data()), json.size(), "gltf", ReadLimits(), &d);
  EXPECT_FALSE(s.ok());
  const std::string off = "OFF\n2000000000 1 0\n0 0 0\n";
  const Status s2 = read_document(reinterpret_cast<const uint8_t*>(off.data()), off.size(), "off", ReadLimits(), &d);
  EXPECT_EQ(s2.kind, ErrorKind::kTooLarge);
}

TEST(MemoryBudget, RefusesPastTheCapNestsAndSurvivesForeignFrees) {
  {
    MemoryBudget outer(64 << 20);
    std::vector<char> small(1 << 20);
    EXPECT_GE(outer.used(), 1 << 20);
    {
      MemoryBudget inner(4 << 20);  // the tighter cap wins
      EXPECT_THROW(std::vector<char>(8 << 20), MemoryLimitExceeded);
      EXPECT_TRUE(inner.exceeded());
    }
    std::vector<char> fits(32 << 20);  // the outer cap again
    EXPECT_THROW(std::vector<char>(64 << 20), MemoryLimitExceeded);
  }
  // Memory allocated on another thread and freed here makes this thread's
  // count negative; a budget must still hold (it once overflowed to "no cap").
  auto foreign = std::make_shared<std::vector<char>>();
  std::thread([&] { foreign->resize(64 << 20); }).join();
  foreign.reset();
  for (int i = 0; i < 2; ++i) {
    MemoryBudget budget(4 << 20);
    EXPECT_THROW(std::vector<char>(16 << 20), MemoryLimitExceeded) << "round " << i;
  }
  // The Draco bombs are refused promptly, again and again on one thread.
  for (const char* bomb : {"crash-draco-bomb-246-bytes.drc", "crash-draco-edgebreaker-bomb.drc"})
    for (int i = 0; i < 2; ++i) {
      const std::vector<uint8_t> bytes = test::read_bytes(test::data_dir() + "/nasty/" + bomb);
      Document doc;
      const Status st = read_document(bytes.data(), bytes.size(), "drc", ReadLimits(), &doc);
      EXPECT_EQ(st.code, "decompression_bomb") << bomb;
      EXPECT_EQ(st.kind, ErrorKind::kTooLarge);
    }
}

// The process-wide cap (the CLI's --memory-limit): past it an allocation on
// any thread is refused, under it the process allocates as before, and with
// no cap (0) nothing is refused.
TEST(MemoryBudget, ProcessCapRefusesOnEveryThread) {
  ASSERT_EQ(process_heap_limit(), 0);
  set_process_heap_limit(current_heap_bytes() + (16 << 20));
  EXPECT_GT(process_heap_limit(), 0);
  {
    std::vector<char> fits(8 << 20);
    EXPECT_THROW(std::vector<char>(16 << 20), MemoryLimitExceeded);
    bool refused = false;
    std::thread([&] {
      try {
        std::vector<char> other(16 << 20);
      } catch (const MemoryLimitExceeded&) {
        refused = true;
      }
    }).join();
    EXPECT_TRUE(refused);
  }
  set_process_heap_limit(0);
  EXPECT_EQ(process_heap_limit(), 0);
  std::vector<char> large(64 << 20);
  EXPECT_EQ(large.size(), size_t(64) << 20);
}

TEST(MemoryBudget, ParsesByteSizesAndTheDefault) {
  int64_t b = -1;
  EXPECT_TRUE(parse_byte_size("0", &b));
  EXPECT_EQ(b, 0);
  EXPECT_TRUE(parse_byte_size("1234", &b));
  EXPECT_EQ(b, 1234);
  EXPECT_TRUE(parse_byte_size("64K", &b));
  EXPECT_EQ(b, 64 << 10);
  EXPECT_TRUE(parse_byte_size("512M", &b));
  EXPECT_EQ(b, int64_t(512) << 20);
  EXPECT_TRUE(parse_byte_size("3G", &b));
  EXPECT_EQ(b, int64_t(3) << 30);
  EXPECT_TRUE(parse_byte_size("1048576G", &b));  // 2^50
  b = -1;
  for (const char* bad : {"", "G", "-1", "+5", " 5", "5 M", "5m", "5MB", "1.5G", "1048577G", "99999999999999999999"})
    EXPECT_FALSE(parse_byte_size(bad, &b)) << bad;
  EXPECT_EQ(b, -1);
  // Three quarters of the machine's memory (or of its container's limit).
  const int64_t physical = int64_t(sysconf(_SC_PHYS_PAGES)) * int64_t(sysconf(_SC_PAGESIZE));
  EXPECT_GT(default_memory_limit(), 0);
  EXPECT_LE(default_memory_limit(), physical / 4 * 3);
}

// A GLB's length fields are 32-bit: a file past 4 GiB is refused (empty),
// before anything is read from the buffer.
TEST(Container, GlbRefusesWhatItsLengthCannotHold) {
  const uint8_t bin[8] = {1, 2, 3, 4, 5, 6, 7, 8};
  const std::vector<uint8_t> glb = pack_glb("{}", bin, sizeof(bin));
  ASSERT_EQ(glb.size(), 12u + 8 + 4 + 8 + 8);
  uint32_t total = 0;
  std::memcpy(&total, glb.data() + 8, 4);
  EXPECT_EQ(total, glb.size());
  EXPECT_TRUE(pack_glb("{}", bin, size_t(1) << 32).empty());
  EXPECT_TRUE(pack_glb("{}", bin, (size_t(1) << 32) - 32).empty());  // with the headers, past 2^32 - 1
}

// Arrays of 2 MB or more are allocated 2 MB-aligned (huge pages): they are
// counted at their size, not at the mapping's slack, and freeing one gives
// back exactly what it was charged, whichever way it is freed.
TEST(MemoryBudget, CountsAlignedArraysAtTheirSize) {
  // (The charges are kept aside in a table: its first allocation stays.)
  // A first pass over the sizes lets that table grow to what they need (run
  // alone, the test failed: the table's growth, 584 bytes, stayed counted
  // after the first size's array was freed).
  const size_t sizes[] = {size_t(3) << 20, (size_t(5) << 20) + 12, size_t(17) << 20};
  for (size_t bytes : sizes) {
    { Array<float> a(bytes / sizeof(float)); }
    ::operator delete(::operator new(bytes, std::align_val_t(kHugePageBytes)), std::align_val_t(kHugePageBytes));
  }
  for (size_t bytes : sizes) {
    const int64_t before = current_heap_bytes();
    {
      Array<float> a(bytes / sizeof(float));
      EXPECT_EQ(reinterpret_cast<uintptr_t>(a.data()) % kHugePageBytes, 0u) << bytes;
      const int64_t held = current_heap_bytes() - before;
      EXPECT_GE(held, int64_t(a.size() * sizeof(float))) << bytes;
      EXPECT_LE(held, int64_t(a.size() * sizeof(float)) + 4096 + 64) << bytes;  // a page, and the table's entry
      a.resize(a.size() / 4);  // shrinks in place; freed below at its capacity
    }
    EXPECT_EQ(current_heap_bytes(), before) << bytes;
    void* p = ::operator new(bytes, std::align_val_t(kHugePageBytes));
    ::operator delete(p, std::align_val_t(kHugePageBytes));  // unsized
    EXPECT_EQ(current_heap_bytes(), before) << bytes;
  }
  MemoryBudget budget(4 << 20);
  EXPECT_THROW(Array<int32_t>(2 << 20), MemoryLimitExceeded);  // 8 MB
}

// Draco output: the POSITION accessor's min/max come from the encoder's own
// quantisation (io/draco_codec.cpp), not from decoding the payload. They
// must be, bit for bit, the bounds of the positions a decoder gets.
struct DracoBounds {
  float lo[3], hi[3];
  int64_t points = 0, faces = 0;
};
DracoBounds decoded_draco_bounds(const EncodeResult& enc) {
  DecodedGeometry g;
  ReadLimits unlimited;
  unlimited.max_vertices = unlimited.max_triangles = INT64_MAX;
  EXPECT_TRUE(draco_decode(enc.bytes.data(), enc.bytes.size(), nullptr, unlimited, &g).ok());
  DracoBounds b;
  b.points = g.points;
  b.faces = int64_t(g.faces.size() / 3);
  for (int k = 0; k < 3; ++k) { b.lo[k] = INFINITY; b.hi[k] = -INFINITY; }
  for (const DecodedAttribute& a : g.attributes) {
    if (a.semantic != "POSITION") continue;
    for (int64_t i = 0; i < g.points; ++i)
      for (int k = 0; k < 3; ++k) {
        b.lo[k] = std::min(b.lo[k], a.data[3 * size_t(i) + k]);
        b.hi[k] = std::max(b.hi[k], a.data[3 * size_t(i) + k]);
      }
  }
  return b;
}

// Encodes positions and faces (with the writer's grid over all the
// positions, or the one the encoder computes) and checks the bounds against
// a decode of the payload; returns the decoded bounds.
DracoBounds check_draco_bounds(const std::vector<float>& pos, const std::vector<int32_t>& faces, bool grid,
                               int bits) {
  EncodeRequest req;
  req.points = int64_t(pos.size() / 3);
  req.faces = &faces;
  req.attributes.push_back({"POSITION", 3, pos.data(), false});
  float origin[3] = {INFINITY, INFINITY, INFINITY}, top[3] = {-INFINITY, -INFINITY, -INFINITY};
  for (size_t i = 0; i < pos.size(); ++i) {
    origin[i % 3] = std::min(origin[i % 3], pos[i]);
    top[i % 3] = std::max(top[i % 3], pos[i]);
  }
  if (grid) {
    req.grid_origin = origin;
    req.grid_range = std::max({top[0] - origin[0], top[1] - origin[1], top[2] - origin[2]});
  }
  OutputOptions opt;
  opt.position_bits = bits;
  EncodeResult enc;
  const Status s = draco_encode(req, opt, &enc);
  EXPECT_TRUE(s.ok()) << s.message;
  const DracoBounds d = decoded_draco_bounds(enc);
  EXPECT_EQ(d.points, enc.points);
  EXPECT_EQ(d.faces, enc.faces);
  for (int k = 0; k < 3; ++k) {
    EXPECT_EQ(enc.pos_min[k], d.lo[k]) << "axis " << k << (grid ? " (grid)" : "") << " bits " << bits;
    EXPECT_EQ(enc.pos_max[k], d.hi[k]) << "axis " << k << (grid ? " (grid)" : "") << " bits " << bits;
  }
  return d;
}

TEST(Draco, PositionBoundsAreTheDecodedOnes) {
  int meshes = 0;
  for (const test::NamedMesh& nm : test::valid_meshes(300000)) {
    SCOPED_TRACE(nm.name);
    const Mesh& m = nm.mesh;
    if (m.num_faces() == 0) continue;
    const std::vector<float> pos(m.positions.begin(), m.positions.end());
    const std::vector<int32_t> faces(m.corner_vertex.begin(), m.corner_vertex.end());
    for (bool grid : {true, false})
      for (int bits : {14, 8}) check_draco_bounds(pos, faces, grid, bits);
    ++meshes;
  }
  EXPECT_GT(meshes, 20);
}

TEST(Draco, PositionBoundsWithUnusedAndRepeatedPoints) {
  // Two triangles of a square, a point no face uses far outside it, and a
  // face that names one point twice (the encoder drops it, and may drop its
  // points): the bounds are still the decoded ones.
  const std::vector<float> pos = {0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0, 50, 50, 50, 5, 5, 5, 6, 5, 5};
  for (bool grid : {true, false}) {
    check_draco_bounds(pos, {0, 1, 2, 0, 2, 3}, grid, 14);
    check_draco_bounds(pos, {0, 1, 2, 0, 2, 3, 5, 6, 6}, grid, 14);
  }
}

TEST(Draco, TinyMeshesKeepTheirShape) {
  // Draco keeps explicit quantisation parameters as six-decimal text: a
  // mesh 1e-8 units across once came out with every point at 0. Its shape
  // must survive within a quantisation step, with the writer's grid or
  // without, and in a whole GLB written and read back.
  Document doc;
  ASSERT_TRUE(test::load(test::data_dir() + "/bunny-npm.obj", &doc).ok());
  Mesh& m = doc.meshes[0].mesh;
  for (float& x : m.positions) x *= 1e-9f;
  const Aabb box = bounding_box(m);
  const std::vector<float> pos(m.positions.begin(), m.positions.end());
  const std::vector<int32_t> faces(m.corner_vertex.begin(), m.corner_vertex.end());
  for (bool grid : {true, false}) {
    const DracoBounds d = check_draco_bounds(pos, faces, grid, 14);
    for (int k = 0; k < 3; ++k) {
      const float step = (box.hi[k] - box.lo[k]) / 16383 + 1e-30f;
      EXPECT_NEAR(d.lo[k], box.lo[k], step) << k;
      EXPECT_NEAR(d.hi[k], box.hi[k], step) << k;
    }
  }
  std::vector<uint8_t> bytes;
  WriteCounts counts;
  ASSERT_TRUE(write_document(doc, OutputOptions(), "glb", nullptr, &bytes, &counts).ok());
  Document back;
  const Status r = read_document(bytes.data(), bytes.size(), "glb", ReadLimits(), &back);
  ASSERT_TRUE(r.ok()) << r.message;
  ASSERT_EQ(back.meshes.size(), 1u);
  EXPECT_EQ(back.meshes[0].mesh.num_faces(), m.num_faces());
  const Aabb out = bounding_box(back.meshes[0].mesh);
  for (int k = 0; k < 3; ++k) EXPECT_NEAR(out.hi[k] - out.lo[k], box.hi[k] - box.lo[k], 1e-3 * (box.hi[k] - box.lo[k])) << k;
}

TEST(Io, DracoPrimitivesOnTwoThreadsGiveTheSameBytes) {
  // A document of two meshes, one cut into three primitives (faces dealt
  // round by index, so every primitive spans the whole mesh), written with
  // Draco on one thread and on two: the same file byte for byte. Then every
  // shipped and corpus glTF file of more than one primitive.
  Document doc;
  ASSERT_TRUE(test::load(test::data_dir() + "/bunny-npm.obj", &doc).ok());
  ASSERT_EQ(doc.meshes.size(), 1u);
  doc.meshes.push_back(doc.meshes[0]);
  MeshSlot& cut = doc.meshes[0];
  cut.mesh.face_group.resize(size_t(cut.mesh.num_faces()));
  for (int32_t f = 0; f < cut.mesh.num_faces(); ++f) cut.mesh.face_group[size_t(f)] = f % 3;
  cut.groups.resize(3, cut.groups[0]);
  for (int g = 0; g < 3; ++g) cut.groups[size_t(g)].gltf_primitive = g;
  std::vector<std::pair<std::string, Document>> docs;
  docs.push_back({"two meshes", std::move(doc)});
  for (const std::string& path : test::valid_mesh_files()) {
    Document d;
    if (!test::load(path, &d).ok() || !d.is_gltf) continue;
    size_t prims = 0;
    for (const MeshSlot& m : d.meshes) prims += m.groups.size();
    if (prims > 1) docs.push_back({path, std::move(d)});
  }
  for (const auto& [name, d] : docs) {
    SCOPED_TRACE(name);
    std::vector<uint8_t> one, two;
    WriteCounts c1, c2;
    OutputOptions opt;
    opt.threads = 1;
    ASSERT_TRUE(write_document(d, opt, "glb", nullptr, &one, &c1).ok());
    opt.threads = 2;
    ASSERT_TRUE(write_document(d, opt, "glb", nullptr, &two, &c2).ok());
    EXPECT_EQ(one, two);
    EXPECT_EQ(c1.primitives, c2.primitives);
    Document back;
    ASSERT_TRUE(read_document(two.data(), two.size(), "glb", ReadLimits(), &back).ok());
    int64_t dropped = 0;
    for (const MeshSlot& s : back.meshes) dropped += s.dropped_faces;
    EXPECT_EQ(triangles(back) + dropped, c2.triangles);
  }
}

TEST(Io, SeveralMeshesRefinedAtOnceGiveTheSameJob) {
  // Three meshes in one GLB, refined by run_job on one thread (one after
  // another) and on two (at once, a thread each): the same output bytes and
  // the same statistics but for the timings, and as many progress calls.
  Document doc;
  for (const char* name : {"bunny-npm.obj", "knot.obj", "suzanne.obj"}) {
    Document one;
    ASSERT_TRUE(test::load(test::data_dir() + "/" + name, &one).ok()) << name;
    doc.meshes.push_back(std::move(one.meshes[0]));
  }
  OutputOptions plain;
  plain.draco = false;
  std::vector<uint8_t> glb;
  WriteCounts wc;
  ASSERT_TRUE(write_document(doc, plain, "glb", nullptr, &glb, &wc).ok());
  std::function<void(nlohmann::json&)> strip_times = [&](nlohmann::json& j) {
    if (j.is_object()) {
      for (const char* key : {"ms", "timings_ms"}) j.erase(key);
      for (auto& v : j) strip_times(v);
    } else if (j.is_array()) {
      for (auto& v : j) strip_times(v);
    }
  };
  for (const char* mode : {"iteas", "uniform"}) {
    SCOPED_TRACE(mode);
    std::vector<uint8_t> out[2];
    nlohmann::json stats[2];
    int calls[2] = {0, 0};
    for (int t = 0; t < 2; ++t) {
      JobRequest rq;
      rq.data = glb.data();
      rq.size = glb.size();
      rq.output_format = "obj";
      rq.options.refine.mode = std::string(mode) == "iteas" ? Mode::kIteas : Mode::kUniform;
      rq.options.refine.levels = 2;
      rq.options.refine.threads = t + 1;
      JobHooks hooks;
      hooks.progress = [&calls, t](int, const char*, double) { ++calls[t]; };
      JobResult res;
      const Status s = run_job(rq, hooks, &res);
      ASSERT_TRUE(s.ok()) << s.message;
      out[t] = res.bytes;
      stats[t] = res.stats;
      strip_times(stats[t]);
    }
    EXPECT_EQ(out[0], out[1]);
    EXPECT_EQ(stats[0], stats[1]);
    EXPECT_EQ(calls[0], calls[1]);
    EXPECT_EQ(stats[1]["meshes"].size(), 3u);
  }
}

TEST(Io, SniffsFormats) {
  for (const auto& [file, fmt] : std::vector<std::pair<std::string, std::string>>{
           {"Box.glb", "glb"}, {"Box.gltf", "gltf"}, {"cube_att.drc", "drc"}, {"eight.off", "off"}, {"bunny-npm.obj", "obj"}}) {
    const std::vector<uint8_t> b = test::read_bytes(test::data_dir() + "/" + file);
    EXPECT_EQ(sniff_format(b.data(), b.size(), ""), fmt) << file;
  }
}

TEST(Io, KeepsWhatIsNotTriangleGeometry) {
  for (const char* name : {"RiggedSimple.glb", "AnimatedMorphCube.glb", "BoxTextured.glb"}) {
    SCOPED_TRACE(name);
    Document in;
    ASSERT_TRUE(test::load(test::data_dir() + "/" + name, &in).ok());
    std::vector<uint8_t> bytes;
    ASSERT_TRUE(write_document(in, OutputOptions(), "glb", nullptr, &bytes, nullptr).ok());
    Document out;
    ASSERT_TRUE(read_document(bytes.data(), bytes.size(), "glb", ReadLimits(), &out).ok());
    for (const char* key : {"nodes", "materials", "skins", "animations", "textures", "images", "samplers", "scenes"}) {
      ASSERT_EQ(in.gltf.contains(key), out.gltf.contains(key)) << key;
      if (!in.gltf.contains(key)) continue;
      if (std::string(key) == "images") {
        EXPECT_EQ(in.gltf[key].size(), out.gltf[key].size());
        continue;
      }
      if (std::string(key) == "skins" || std::string(key) == "animations") {
        // Accessor indices are renumbered; the structure and counts are kept.
        EXPECT_EQ(in.gltf[key].size(), out.gltf[key].size());
        continue;
      }
      EXPECT_EQ(in.gltf[key], out.gltf[key]) << key;
    }
  }
}

// The text readers parse plain decimals with std::from_chars and anything
// else with the C functions: every number must still read as strtof (OBJ)
// or strtod then float (OFF, ASCII PLY) read it, in every form (signs, '+',
// no leading or trailing digit, exponents, 9 and 17 digits, subnormals, hex,
// leading zeros), and a malformed one must still be refused.
TEST(Io, TextNumbersReadAsTheCFunctionsReadThem) {
  std::vector<std::string> tokens = {"0", "-0", "+1.5", ".5", "-.25", "5.", "1e3", "1E-3", "+2e+2", "007.50",
                                     "0x1p3", "-0x1.8p-1", "1e-40", "-1.4e-45", "3.4028234e38", "123456789012345678"};
  std::mt19937_64 g(11);
  for (int i = 0; i < 3000; ++i) {
    const double x = std::ldexp(double(g() >> 11), int(g() % 120) - 90) * (g() % 2 ? -1 : 1);
    char buf[64];
    std::snprintf(buf, sizeof buf, i % 3 == 0 ? "%.9g" : (i % 3 == 1 ? "%.17g" : "%.6e"), x);
    tokens.push_back(buf);
  }
  // Vertex k is (token k, k, 0): distinct, so the welded positions keep their order.
  std::string obj, off = "OFF\n" + std::to_string(tokens.size()) + " " + std::to_string(tokens.size() / 3) + " 0\n",
                   ply = "ply\nformat ascii 1.0\nelement vertex " + std::to_string(tokens.size()) +
                         "\nproperty float x\nproperty float y\nproperty float z\nelement face " +
                         std::to_string(tokens.size() / 3) + "\nproperty list uchar int vertex_indices\nend_header\n";
  for (size_t k = 0; k < tokens.size(); ++k) {
    obj += "v " + tokens[k] + " " + std::to_string(k) + " 0\n";
    off += tokens[k] + " " + std::to_string(k) + " 0\n";
    ply += tokens[k] + " " + std::to_string(k) + " 0\n";
  }
  for (size_t f = 0; f < tokens.size() / 3; ++f) {
    obj += "f " + std::to_string(3 * f + 1) + " " + std::to_string(3 * f + 2) + " " + std::to_string(3 * f + 3) + "\n";
    const std::string tri = std::to_string(3 * f) + " " + std::to_string(3 * f + 1) + " " + std::to_string(3 * f + 2) + "\n";
    off += "3 " + tri;
    ply += "3 " + tri;
  }
  for (const auto& [fmt, text] : std::vector<std::pair<std::string, std::string>>{{"obj", obj}, {"off", off}, {"ply", ply}}) {
    Document d;
    const Status st = read_document(reinterpret_cast<const uint8_t*>(text.data()), text.size(), fmt, ReadLimits(), &d);
    ASSERT_TRUE(st.ok()) << fmt << ": " << st.message;
    ASSERT_EQ(d.meshes.size(), 1u);
    const Mesh& m = d.meshes[0].mesh;
    ASSERT_EQ(size_t(m.num_vertices()), tokens.size() / 3 * 3) << fmt;
    int differ = 0;
    for (int32_t v = 0; v < m.num_vertices(); ++v) {
      const std::string& t = tokens[size_t(v)];
      const float want = fmt == "obj" ? std::strtof(t.c_str(), nullptr) : float(std::strtod(t.c_str(), nullptr));
      const float got = m.positions[3 * size_t(v)];
      if (std::memcmp(&want, &got, 4) != 0 && ++differ <= 3) ADD_FAILURE() << fmt << " '" << t << "': " << got << " vs " << want;
      EXPECT_EQ(m.positions[3 * size_t(v) + 1], float(v)) << fmt;
    }
    EXPECT_EQ(differ, 0) << fmt;
  }
  for (const std::string bad : {"1.5x", "1e", "--1", "1..2", "0x", "1,5"}) {
    for (const auto& [fmt, text] : std::vector<std::pair<std::string, std::string>>{
             {"obj", "v " + bad + " 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"},
             {"off", "OFF\n3 1 0\n" + bad + " 0 0\n1 0 0\n0 1 0\n3 0 1 2\n"}}) {
      Document d;
      EXPECT_FALSE(read_document(reinterpret_cast<const uint8_t*>(text.data()), text.size(), fmt, ReadLimits(), &d).ok())
          << fmt << " '" << bad << "'";
    }
  }
}

TEST(Options, ParsesAndNamesBadOptions) {
  Options o;
  std::string err, bad;
  EXPECT_TRUE(parse_options({{"mode", "uniform"}, {"levels", "3"}, {"crease-angle", "40"}}, &o, &err));
  EXPECT_EQ(o.refine.mode, Mode::kUniform);
  EXPECT_EQ(o.refine.levels, 3);
  EXPECT_EQ(o.refine.crease_angle, 40);
  Options d;
  EXPECT_TRUE(parse_options({}, &d, &err));
  EXPECT_EQ(d.refine.levels, 6);
  EXPECT_TRUE(parse_options({{"mode", "uniform"}}, &d, &err));
  EXPECT_EQ(d.refine.levels, 2);
  for (const auto& [k, v] : std::vector<std::pair<std::string, std::string>>{
           {"levels", "9"}, {"levels", "x"}, {"mode", "loop"}, {"tension", "0.5"}, {"threshold", "p101"},
           {"position_bits", "7"}, {"bogus", "1"}, {"max_triangles", "-3"}, {"crease_angle", "nan"},
           {"stall_ratio", "0"}, {"stall_ratio", "1.5"}, {"stall_ratio", "half"}, {"tolerance", "0"},
           {"tolerance", "-0.001"}, {"tolerance", "2"}, {"flat_limit", "1e400"}, {"flat_limit", "on"}}) {
    Options x;
    EXPECT_FALSE(parse_options({{k, v}}, &x, &err, &bad)) << k << "=" << v;
    EXPECT_EQ(bad, k);
    EXPECT_NE(err.find(k), std::string::npos);
  }
  Options f;
  EXPECT_FALSE(parse_options({{"mode", "fixed"}}, &f, &err, &bad));
  EXPECT_EQ(bad, "threshold");
  // max_triangles past what 32-bit corner indices number is capped to it.
  Options big, most;
  EXPECT_TRUE(parse_options({{"max_triangles", "99999999999"}}, &big, &err));
  EXPECT_EQ(big.refine.max_triangles, kMaxTriangles);
  EXPECT_TRUE(parse_options({{"max_triangles", std::to_string(kMaxTriangles)}}, &most, &err));
  EXPECT_EQ(most.refine.max_triangles, kMaxTriangles);
}

// The stall ratio: on by default in iteas mode, off for the thesis's fixed
// threshold unless asked for, never for uniform or select=below.
TEST(Options, StallRatioDefaultsPerMode) {
  std::string err;
  Options it, fx, fx_on, un, below, off;
  ASSERT_TRUE(parse_options({}, &it, &err));
  EXPECT_DOUBLE_EQ(effective_stall_ratio(it.refine), kStallRatioDefault);
  ASSERT_TRUE(parse_options({{"mode", "fixed"}, {"threshold", "10"}}, &fx, &err));
  EXPECT_EQ(effective_stall_ratio(fx.refine), 0);
  ASSERT_TRUE(parse_options({{"mode", "fixed"}, {"threshold", "10"}, {"stall-ratio", "0.6"}}, &fx_on, &err));
  EXPECT_DOUBLE_EQ(effective_stall_ratio(fx_on.refine), 0.6);
  ASSERT_TRUE(parse_options({{"mode", "uniform"}, {"stall_ratio", "0.6"}}, &un, &err));
  EXPECT_EQ(effective_stall_ratio(un.refine), 0);
  ASSERT_TRUE(parse_options({{"select", "below"}}, &below, &err));
  EXPECT_EQ(effective_stall_ratio(below.refine), 0);
  ASSERT_TRUE(parse_options({{"stall_ratio", "off"}}, &off, &err));
  EXPECT_EQ(effective_stall_ratio(off.refine), 0);
}

// The geometric tolerances: on by default in iteas mode (select=above), off
// for the thesis's fixed threshold unless asked for, never for uniform.
TEST(Options, TolerancesDefaultPerMode) {
  std::string err;
  Options it, fx, fx_on, un, below, below_on, off;
  ASSERT_TRUE(parse_options({}, &it, &err));
  EXPECT_DOUBLE_EQ(effective_tolerance(it.refine), kToleranceDefault);
  EXPECT_DOUBLE_EQ(effective_flat_limit(it.refine), kFlatLimitDefault);
  ASSERT_TRUE(parse_options({{"mode", "fixed"}, {"threshold", "10"}}, &fx, &err));
  EXPECT_EQ(effective_tolerance(fx.refine), 0);
  EXPECT_EQ(effective_flat_limit(fx.refine), 0);
  ASSERT_TRUE(parse_options({{"mode", "fixed"}, {"threshold", "10"}, {"tolerance", "0.001"}, {"flat-limit", "0.01"}},
                            &fx_on, &err));
  EXPECT_DOUBLE_EQ(effective_tolerance(fx_on.refine), 0.001);
  EXPECT_DOUBLE_EQ(effective_flat_limit(fx_on.refine), 0.01);
  ASSERT_TRUE(parse_options({{"mode", "uniform"}, {"tolerance", "0.001"}}, &un, &err));
  EXPECT_EQ(effective_tolerance(un.refine), 0);
  ASSERT_TRUE(parse_options({{"select", "below"}}, &below, &err));
  EXPECT_EQ(effective_tolerance(below.refine), 0);
  EXPECT_EQ(effective_flat_limit(below.refine), 0);
  ASSERT_TRUE(parse_options({{"select", "below"}, {"tolerance", "0.001"}}, &below_on, &err));
  EXPECT_DOUBLE_EQ(effective_tolerance(below_on.refine), 0.001);
  ASSERT_TRUE(parse_options({{"tolerance", "off"}, {"flat_limit", "off"}}, &off, &err));
  EXPECT_EQ(effective_tolerance(off.refine), 0);
  EXPECT_EQ(effective_flat_limit(off.refine), 0);
}

}  // namespace
}  // namespace iteas
