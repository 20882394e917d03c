// Raw Draco (.drc, through Draco's decoder), OBJ, PLY, OFF and STL (parsers
// of our own, limits checked before allocating), and the .drc / .obj / .ply
// writers.
#include <algorithm>
#include <array>
#include <charconv>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <map>
#include <sstream>
#include <string_view>
#include <type_traits>
#include <unordered_map>


#include "io/container.h"
#include "io/document.h"
#include "io/draco_codec.h"

namespace iteas {
namespace {

Status bad(const std::string& code, const std::string& msg) { return Status::Error(ErrorKind::kBadInput, code, msg); }

// A flat triangle soup with per-point attributes, welded into one MeshSlot.
Status slot_from_geometry(DecodedGeometry& g, const std::string& name, Document* doc) {
  const DecodedAttribute* pos = nullptr;
  for (const DecodedAttribute& a : g.attributes)
    if (a.semantic == "POSITION") pos = &a;
  if (!pos || pos->components != 3) return bad("no_positions", "the mesh has no 3D positions");
  for (float x : pos->data)
    if (!std::isfinite(x)) return Status::Error(ErrorKind::kUnusable, "non_finite_positions", "the mesh has non-finite vertex positions");
  MeshSlot slot;
  slot.name = name;
  Mesh& m = slot.mesh;
  for (const DecodedAttribute& a : g.attributes) {
    if (a.semantic == "POSITION") continue;
    Channel ch;
    ch.name = a.semantic;
    ch.components = a.components;
    ch.kind = a.semantic == "NORMAL" ? ChannelKind::kNormal : ChannelKind::kLinear;
    m.channels.push_back(std::move(ch));
  }
  Welder weld;
  std::vector<int32_t> wedge(size_t(g.points), -1);
  for (size_t i = 0; i < g.faces.size(); ++i) {
    const int32_t p = g.faces[i];
    if (wedge[p] < 0) {
      const auto [vertex, inserted] = weld.weld(&pos->data[3 * size_t(p)], m.num_vertices());
      if (inserted) for (int k = 0; k < 3; ++k) m.positions.push_back(pos->data[3 * size_t(p) + k]);
      const int32_t w = m.add_wedge(vertex);
      size_t ci = 0;
      for (const DecodedAttribute& a : g.attributes) {
        if (a.semantic == "POSITION") continue;
        Channel& ch = m.channels[ci++];
        for (int k = 0; k < ch.components; ++k) ch.data[size_t(w) * ch.components + k] = a.data[size_t(p) * a.components + k];
      }
      wedge[p] = w;
    }
    m.corner_vertex.push_back(m.wedge_vertex[wedge[p]]);
    m.corner_wedge.push_back(wedge[p]);
    if (i % 3 == 2) m.face_group.push_back(0);
  }
  GroupInfo gi;
  gi.gltf_primitive = 0;
  gi.has_channel.assign(m.channels.size(), 1);
  slot.groups.push_back(gi);
  slot.input_primitives = 1;
  slot.input_triangles = int64_t(g.faces.size() / 3);
  slot.input_vertices = g.points;
  slot.welded_vertices = m.num_vertices();
  doc->meshes.push_back(std::move(slot));
  return Status::Ok();
}

// Blanks as std::isspace and istream >> see them in the C locale (the
// program never sets another): space, \t, \n, \v, \f, \r.
inline bool blank(char c) { return c == ' ' || (c >= '\t' && c <= '\r'); }

// [s, e) read whole as a number, with the result strtod, strtof or strtoll
// give: std::from_chars for the plain decimal forms (correctly rounded, as
// they are, with no copy of the token), the C function itself for anything
// else ('+', hex, inf, nan, a value out of range, a malformed token).
template <typename T>
bool parse_whole(const char* s, const char* e, T* v) {
  if (s < e && ((*s >= '0' && *s <= '9') || *s == '-' || *s == '.')) {
    T x;
    const std::from_chars_result r = std::from_chars(s, e, x);
    bool plain = r.ec == std::errc() && r.ptr == e;
    if constexpr (std::is_floating_point_v<T>) plain = plain && std::isfinite(x);
    if (plain) {
      *v = x;
      return true;
    }
  }
  const std::string t(s, e);
  char* end = nullptr;
  if constexpr (std::is_same_v<T, double>) *v = std::strtod(t.c_str(), &end);
  else if constexpr (std::is_same_v<T, float>) *v = std::strtof(t.c_str(), &end);
  else *v = std::strtoll(t.c_str(), &end, 10);
  return !t.empty() && end == t.c_str() + t.size();
}

// Whitespace tokenizer over untrusted text ('#' starts a comment to the line's end).
struct Tokens {
  const char* p;
  const char* end;
  bool next(const char** s, const char** e) {
    while (p < end) {
      if (*p == '#') { while (p < end && *p != '\n') ++p; continue; }
      if (blank(*p)) { ++p; continue; }
      break;
    }
    if (p >= end) return false;
    *s = p;
    while (p < end && !blank(*p) && *p != '#') ++p;
    *e = p;
    return true;
  }
  bool next(std::string* out) {
    const char *s, *e;
    if (!next(&s, &e)) return false;
    out->assign(s, e);
    return true;
  }
  bool number(double* v) {
    const char *s, *e;
    return next(&s, &e) && parse_whole(s, e, v);
  }
  bool integer(int64_t* v) {
    const char *s, *e;
    long long x = 0;
    if (!next(&s, &e) || !parse_whole(s, e, &x)) return false;
    *v = x;
    return true;
  }
};

// The blank-separated words of one line, as istream >> reads them.
struct Words {
  const char* p;
  const char* end;
  bool next(std::string_view* w) {
    while (p < end && blank(*p)) ++p;
    if (p >= end) return false;
    const char* s = p;
    while (p < end && !blank(*p)) ++p;
    *w = std::string_view(s, size_t(p - s));
    return true;
  }
};

Status read_off(const uint8_t* data, size_t size, const ReadLimits& limits, DecodedGeometry* g) {
  Tokens t{reinterpret_cast<const char*>(data), reinterpret_cast<const char*>(data) + size};
  std::string head;
  if (!t.next(&head) || head != "OFF") return bad("bad_off", "OFF header missing");
  int64_t nv, nf, ne;
  if (!t.integer(&nv) || !t.integer(&nf) || !t.integer(&ne) || nv < 0 || nf < 0)
    return bad("bad_off", "OFF counts missing or negative");
  // Every vertex needs at least 6 bytes of text and every face 8: check first.
  if (nv > limits.max_vertices || nf > limits.max_triangles || nv * 6 > int64_t(size) || nf * 8 > int64_t(size))
    return Status::Error(ErrorKind::kTooLarge, "too_large", "OFF declares more vertices or faces than it holds");
  DecodedAttribute pos{"POSITION", 3, std::vector<float>(size_t(nv) * 3)};
  for (int64_t i = 0; i < 3 * nv; ++i) {
    double v;
    if (!t.number(&v)) return bad("bad_off", "OFF vertex " + std::to_string(i / 3) + " is malformed");
    pos.data[size_t(i)] = float(v);
  }
  for (int64_t f = 0; f < nf; ++f) {
    int64_t n;
    if (!t.integer(&n) || n < 3 || n > 1024) return bad("bad_off", "OFF face " + std::to_string(f) + " is malformed");
    int64_t first = 0, prev = 0;
    for (int64_t k = 0; k < n; ++k) {
      int64_t idx;
      if (!t.integer(&idx) || idx < 0 || idx >= nv) return bad("index_out_of_range", "OFF face " + std::to_string(f) + " has a bad index");
      if (k == 0) first = idx;
      else if (k >= 2) g->faces.insert(g->faces.end(), {int32_t(first), int32_t(prev), int32_t(idx)});
      prev = idx;
    }
    // Anything else on the face line (colours) is skipped by the next count read
    // only if numeric; we stop at the line end instead.
    while (t.p < t.end && *t.p != '\n') ++t.p;
    if (int64_t(g->faces.size() / 3) > limits.max_triangles)
      return Status::Error(ErrorKind::kTooLarge, "too_large", "OFF has too many triangles");
  }
  g->points = nv;
  g->attributes.push_back(std::move(pos));
  return Status::Ok();
}

// OBJ: v / vt / vn / f (polygons fanned), negative indices, every index checked.
// Our own parser: Draco's OBJ decoder crashes on face entries without a
// position index (found by fuzz/fuzz_read, reproducer in fuzz/corpus).
Status read_obj(const uint8_t* data, size_t size, const ReadLimits& limits, DecodedGeometry* g) {
  std::vector<float> v, vt, vn;
  struct Corner { int32_t v, t, n; };
  std::vector<Corner> corners, poly;  // 3 per triangle; a face line's
  const char* p = reinterpret_cast<const char*>(data);
  const char* end = p + size;
  int64_t line_no = 0;
  auto bad_line = [&](const std::string& what) { return bad("bad_obj", "OBJ line " + std::to_string(line_no) + ": " + what); };
  while (p < end) {
    const char* eol = static_cast<const char*>(std::memchr(p, '\n', size_t(end - p)));
    if (!eol) eol = end;
    const char* hash = static_cast<const char*>(std::memchr(p, '#', size_t(eol - p)));
    Words in{p, hash ? hash : eol};
    p = eol + 1;
    ++line_no;
    std::string_view key;
    if (!in.next(&key)) continue;
    if (key == "v" || key == "vn" || key == "vt") {
      std::vector<float>& dst = key == "v" ? v : (key == "vn" ? vn : vt);
      const int want = key == "vt" ? 2 : 3;
      for (int k = 0; k < want; ++k) {
        std::string_view tok;
        if (!in.next(&tok)) {
          if (key == "vt" && k == 1) { dst.push_back(0.0f); continue; }  // 1D texture coordinate
          return bad_line("too few coordinates");
        }
        float x;
        if (!parse_whole(tok.data(), tok.data() + tok.size(), &x))
          return bad_line("malformed number '" + std::string(tok.substr(0, 32)) + "'");
        dst.push_back(x);
      }
      if (int64_t(v.size() / 3) > limits.max_vertices) return Status::Error(ErrorKind::kTooLarge, "too_large", "OBJ has too many vertices");
    } else if (key == "f") {
      poly.clear();
      std::string_view tok;
      while (in.next(&tok)) {
        Corner c{-1, -1, -1};
        int32_t* slot[3] = {&c.v, &c.t, &c.n};
        const int64_t counts[3] = {int64_t(v.size() / 3), int64_t(vt.size() / 2), int64_t(vn.size() / 3)};
        size_t pos = 0;
        for (int part = 0; part < 3 && pos <= tok.size(); ++part) {
          const size_t slash = std::min(tok.find('/', pos), tok.size());
          const std::string_view num = tok.substr(pos, slash - pos);
          pos = slash + 1;
          if (num.empty()) {
            if (part == 0) return bad_line("face entry '" + std::string(tok.substr(0, 32)) + "' has no vertex index");
            continue;
          }
          long long i = 0;
          if (!parse_whole(num.data(), num.data() + num.size(), &i))
            return bad_line("malformed index '" + std::string(num.substr(0, 32)) + "'");
          const long long resolved = i < 0 ? counts[part] + i : i - 1;
          if (i == 0 || resolved < 0 || resolved >= counts[part])
            return bad("index_out_of_range", "OBJ line " + std::to_string(line_no) + ": index " + std::string(num.substr(0, 32)) + " is out of range");
          *slot[part] = int32_t(resolved);
          if (slash >= tok.size()) break;
        }
        poly.push_back(c);
      }
      if (poly.size() < 3) continue;  // points and lines are not triangles
      for (size_t k = 2; k < poly.size(); ++k) corners.insert(corners.end(), {poly[0], poly[k - 1], poly[k]});
      if (int64_t(corners.size() / 3) > limits.max_triangles)
        return Status::Error(ErrorKind::kTooLarge, "too_large", "OBJ has too many triangles");
    }
    // o, g, s, usemtl, mtllib, l, ...: not geometry we refine.
  }
  // One point per distinct (position, texcoord, normal) triple.
  bool any_t = false, any_n = false;
  for (const Corner& c : corners) { any_t = any_t || c.t >= 0; any_n = any_n || c.n >= 0; }
  // Numbered in order of first use; positions alone are looked up by index,
  // triples in an ordered map (no hash whose collisions a file could choose).
  std::map<std::array<int32_t, 3>, int32_t> point_of;
  std::vector<int32_t> point_of_position(any_t || any_n ? 0 : v.size() / 3, -1);
  int32_t points = 0;
  DecodedAttribute pos{"POSITION", 3, {}}, uv{"TEXCOORD_0", 2, {}}, nor{"NORMAL", 3, {}};
  g->faces.reserve(corners.size());
  for (const Corner& c : corners) {
    int32_t* found;
    if (any_t || any_n) found = &point_of.emplace(std::array<int32_t, 3>{c.v, c.t, c.n}, -1).first->second;
    else found = &point_of_position[size_t(c.v)];
    if (*found < 0) {
      *found = points++;
      for (int k = 0; k < 3; ++k) pos.data.push_back(v[3 * size_t(c.v) + k]);
      if (any_t) for (int k = 0; k < 2; ++k) uv.data.push_back(c.t >= 0 ? vt[2 * size_t(c.t) + k] : 0.0f);
      if (any_n) for (int k = 0; k < 3; ++k) nor.data.push_back(c.n >= 0 ? vn[3 * size_t(c.n) + k] : 0.0f);
    }
    g->faces.push_back(*found);
  }
  g->points = points;
  g->attributes.push_back(std::move(pos));
  if (any_n) g->attributes.push_back(std::move(nor));
  if (any_t) g->attributes.push_back(std::move(uv));
  return Status::Ok();
}

// PLY: ASCII and binary (either endianness). Our own parser: Draco's PLY
// decoder crashes on out-of-range face indices (found by fuzz/fuzz_read).
Status read_ply(const uint8_t* data, size_t size, const ReadLimits& limits, DecodedGeometry* g) {
  struct Property { std::string name; int type = 0; int count_type = 0; bool list = false; };
  struct Element { std::string name; int64_t count = 0; std::vector<Property> props; };
  auto type_size = [](const std::string& t) -> int {
    if (t == "char" || t == "int8" || t == "uchar" || t == "uint8") return t[0] == 'u' ? 11 : 1;
    if (t == "short" || t == "int16") return 2;
    if (t == "ushort" || t == "uint16") return 12;
    if (t == "int" || t == "int32") return 4;
    if (t == "uint" || t == "uint32") return 14;
    if (t == "float" || t == "float32") return 24;
    if (t == "double" || t == "float64") return 28;
    return 0;
  };  // code: size + 10 unsigned, + 20 floating
  const char* text = reinterpret_cast<const char*>(data);
  const char* hend = nullptr;
  for (size_t i = 0; i + 11 <= size && i < (1u << 20); ++i)
    if (std::memcmp(text + i, "end_header", 10) == 0 && (text[i + 10] == '\n' || text[i + 10] == '\r')) {
      hend = text + i + 10;
      break;
    }
  if (!hend) return bad("bad_ply", "PLY header has no end_header");
  while (hend < text + size && *hend != '\n') ++hend;
  if (hend < text + size) ++hend;  // past the '\n', never past the end (a header ending in "\r")
  std::istringstream header(std::string(text, hend));
  std::string line, format;
  std::vector<Element> elements;
  while (std::getline(header, line)) {
    std::istringstream in(line);
    std::string key;
    in >> key;
    if (key == "format") in >> format;
    else if (key == "element") {
      Element e;
      if (!(in >> e.name >> e.count) || e.count < 0) return bad("bad_ply", "PLY element line is malformed");
      elements.push_back(e);
    } else if (key == "property") {
      if (elements.empty()) return bad("bad_ply", "PLY property before any element");
      Property pr;
      std::string t;
      in >> t;
      if (t == "list") {
        std::string ct, it;
        in >> ct >> it >> pr.name;
        pr.list = true;
        pr.count_type = type_size(ct);
        pr.type = type_size(it);
        if (!pr.count_type || !pr.type || pr.count_type >= 20) return bad("bad_ply", "PLY list property has a bad type");
      } else {
        in >> pr.name;
        pr.type = type_size(t);
        if (!pr.type) return bad("bad_ply", "PLY property type '" + t.substr(0, 16) + "' is unknown");
      }
      elements.back().props.push_back(pr);
    }
  }
  const bool ascii = format == "ascii", little = format == "binary_little_endian", big = format == "binary_big_endian";
  if (!ascii && !little && !big) return bad("bad_ply", "PLY format must be ascii or binary");
  const uint8_t* b = reinterpret_cast<const uint8_t*>(hend);
  const uint8_t* bend = data + size;
  Tokens tok{hend, text + size};
  bool ok = true;
  auto read = [&](int code) -> double {
    if (ascii) {
      double v = 0;
      if (!tok.number(&v)) ok = false;
      return v;
    }
    const int n = code % 10;
    if (bend - b < n) { ok = false; return 0; }
    uint8_t raw[8];
    for (int i = 0; i < n; ++i) raw[i] = big ? b[n - 1 - i] : b[i];
    b += n;
    if (code >= 20) {
      if (n == 4) { float f; std::memcpy(&f, raw, 4); return f; }
      double d; std::memcpy(&d, raw, 8); return d;
    }
    uint64_t u = 0;
    std::memcpy(&u, raw, size_t(n));
    if (code >= 10) return double(u);
    const int shift = 64 - 8 * n;
    return double(int64_t(u << shift) >> shift);
  };
  DecodedAttribute pos{"POSITION", 3, {}}, nor{"NORMAL", 3, {}}, col{"COLOR_0", 3, {}}, uv{"TEXCOORD_0", 2, {}};
  int64_t nverts = -1;
  for (const Element& e : elements) {
    // Every element takes at least one byte (binary) or two (ASCII) per property.
    const int64_t min_bytes = std::max<int64_t>(1, int64_t(e.props.size()));
    if (e.count > int64_t(size) / min_bytes) return Status::Error(ErrorKind::kTooLarge, "too_large", "PLY declares more elements than it holds");
    const bool is_vertex = e.name == "vertex", is_face = e.name == "face";
    if (is_vertex && e.count > limits.max_vertices) return Status::Error(ErrorKind::kTooLarge, "too_large", "PLY has too many vertices");
    int ix = -1, iy = -1, iz = -1, inx = -1, iny = -1, inz = -1, ir = -1, ig = -1, ib = -1, iu = -1, iv = -1, ilist = -1;
    for (size_t k = 0; k < e.props.size(); ++k) {
      const std::string& n = e.props[k].name;
      const int kk = int(k);
      if (n == "x") ix = kk; else if (n == "y") iy = kk; else if (n == "z") iz = kk;
      else if (n == "nx") inx = kk; else if (n == "ny") iny = kk; else if (n == "nz") inz = kk;
      else if (n == "red") ir = kk; else if (n == "green") ig = kk; else if (n == "blue") ib = kk;
      else if (n == "s" || n == "u" || n == "texture_u") iu = kk; else if (n == "t" || n == "v" || n == "texture_v") iv = kk;
      else if ((n == "vertex_indices" || n == "vertex_index") && e.props[k].list) ilist = kk;
    }
    if (is_vertex && (ix < 0 || iy < 0 || iz < 0)) return bad("bad_ply", "PLY vertices have no x, y, z");
    std::vector<double> vals(e.props.size());
    std::vector<int64_t> poly;
    for (int64_t r = 0; r < e.count; ++r) {
      for (size_t k = 0; k < e.props.size(); ++k) {
        const Property& pr = e.props[k];
        if (!pr.list) { vals[k] = read(pr.type); continue; }
        const double cnt = read(pr.count_type);
        if (!ok || !(cnt >= 0 && cnt <= 1024)) return bad("bad_ply", "PLY list length is out of range");
        poly.clear();
        for (int i = 0; i < int(cnt); ++i) {
          const double v = read(pr.type);  // any type, even float: out of range (or NaN) is -1, refused below
          poly.push_back(v >= 0 && v < 2147483648.0 ? int64_t(v) : -1);
        }
        if (is_face && int(k) == ilist) {
          for (int64_t idx : poly)
            if (idx < 0 || idx >= nverts) return bad("index_out_of_range", "PLY face references a missing vertex");
          for (size_t i = 2; i < poly.size(); ++i)
            g->faces.insert(g->faces.end(), {int32_t(poly[0]), int32_t(poly[i - 1]), int32_t(poly[i])});
          if (int64_t(g->faces.size() / 3) > limits.max_triangles) return Status::Error(ErrorKind::kTooLarge, "too_large", "PLY has too many triangles");
        }
      }
      if (!ok) return bad("bad_ply", "PLY data ends early or is malformed");
      if (is_vertex) {
        for (int k : {ix, iy, iz}) pos.data.push_back(float(vals[k]));
        if (inx >= 0 && iny >= 0 && inz >= 0) for (int k : {inx, iny, inz}) nor.data.push_back(float(vals[k]));
        if (ir >= 0 && ig >= 0 && ib >= 0)
          for (int k : {ir, ig, ib}) col.data.push_back(float(e.props[k].type < 20 ? vals[k] / 255.0 : vals[k]));
        if (iu >= 0 && iv >= 0) for (int k : {iu, iv}) uv.data.push_back(float(vals[k]));
      }
    }
    if (is_vertex) nverts = e.count;
  }
  if (nverts < 0) return bad("bad_ply", "PLY has no vertex element");
  g->points = nverts;
  g->attributes.push_back(std::move(pos));
  if (!nor.data.empty()) g->attributes.push_back(std::move(nor));
  if (!col.data.empty()) g->attributes.push_back(std::move(col));
  if (!uv.data.empty()) g->attributes.push_back(std::move(uv));
  return Status::Ok();
}

Status read_stl(const uint8_t* data, size_t size, const ReadLimits& limits, DecodedGeometry* g) {
  DecodedAttribute pos{"POSITION", 3, {}};
  bool binary = false;
  if (size >= 84) {
    uint32_t n;
    std::memcpy(&n, data + 80, 4);
    binary = uint64_t(84) + uint64_t(n) * 50 == size;
  }
  if (binary) {
    uint32_t n;
    std::memcpy(&n, data + 80, 4);
    if (int64_t(n) > limits.max_triangles) return Status::Error(ErrorKind::kTooLarge, "too_large", "STL has too many triangles");
    pos.data.resize(size_t(n) * 9);
    for (uint32_t f = 0; f < n; ++f) std::memcpy(&pos.data[size_t(f) * 9], data + 84 + size_t(f) * 50 + 12, 36);
  } else {
    Tokens t{reinterpret_cast<const char*>(data), reinterpret_cast<const char*>(data) + size};
    std::string tok;
    if (!t.next(&tok) || tok != "solid") return bad("bad_stl", "neither binary STL nor ASCII 'solid'");
    while (t.next(&tok)) {
      if (tok != "vertex") continue;
      for (int k = 0; k < 3; ++k) {
        double v;
        if (!t.number(&v)) return bad("bad_stl", "STL vertex is malformed");
        pos.data.push_back(float(v));
      }
      if (int64_t(pos.data.size() / 9) > limits.max_triangles) return Status::Error(ErrorKind::kTooLarge, "too_large", "STL has too many triangles");
    }
    pos.data.resize(pos.data.size() / 9 * 9);
  }
  g->points = int64_t(pos.data.size() / 3);
  g->faces.resize(size_t(g->points));
  for (int64_t i = 0; i < g->points; ++i) g->faces[size_t(i)] = int32_t(i);
  g->attributes.push_back(std::move(pos));
  return Status::Ok();
}

// Writers take the whole document as one mesh (all slots appended).
struct Flat {
  std::vector<float> pos;      // per wedge
  std::vector<float> normal;   // per wedge, may be empty
  std::vector<float> uv;       // per wedge, may be empty
  std::vector<int32_t> faces;  // wedge indices
};

Flat flatten(const Document& doc) {
  Flat f;
  bool all_normals = !doc.meshes.empty(), all_uv = !doc.meshes.empty();
  for (const MeshSlot& s : doc.meshes) {
    all_normals = all_normals && s.mesh.find_channel("NORMAL") >= 0;
    all_uv = all_uv && s.mesh.find_channel("TEXCOORD_0") >= 0;
  }
  for (const MeshSlot& s : doc.meshes) {
    const Mesh& m = s.mesh;
    const int32_t base = int32_t(f.pos.size() / 3), nw = m.wedge_count();
    const int ni = m.find_channel("NORMAL"), ti = m.find_channel("TEXCOORD_0");
    for (int32_t w = 0; w < nw; ++w) {
      const int32_t v = m.has_wedges() ? m.wedge_vertex[w] : w;
      for (int k = 0; k < 3; ++k) f.pos.push_back(m.positions[3 * size_t(v) + k]);
      if (all_normals) for (int k = 0; k < 3; ++k) f.normal.push_back(m.channels[ni].data[3 * size_t(w) + k]);
      if (all_uv) for (int k = 0; k < 2; ++k) f.uv.push_back(m.channels[ti].data[size_t(w) * m.channels[ti].components + k]);
    }
    for (int32_t c = 0; c < int32_t(m.corner_vertex.size()); ++c) f.faces.push_back(base + m.wedge_of(c));
  }
  return f;
}

}  // namespace

Status read_classic(const uint8_t* data, size_t size, const std::string& format, const ReadLimits& limits, Document* doc) {
  DecodedGeometry g;
  Status s;
  if (format == "drc") {
    s = draco_decode(data, size, nullptr, limits, &g);
  } else if (format == "off") {
    s = read_off(data, size, limits, &g);
  } else if (format == "stl") {
    s = read_stl(data, size, limits, &g);
  } else if (format == "obj") {
    s = read_obj(data, size, limits, &g);
  } else if (format == "ply") {
    s = read_ply(data, size, limits, &g);
  } else {
    return Status::Error(ErrorKind::kUnsupported, "unsupported_format", "unknown input format");
  }
  if (!s.ok()) return s;
  for (int32_t i : g.faces)
    if (i < 0 || int64_t(i) >= g.points) return bad("index_out_of_range", "a face references a missing vertex");
  return slot_from_geometry(g, "mesh", doc);
}

Status write_classic(const Document& doc, const OutputOptions& opt, const std::string& format, std::vector<uint8_t>* out,
                     WriteCounts* counts) {
  const Flat f = flatten(doc);
  const int64_t nw = int64_t(f.pos.size() / 3), nf = int64_t(f.faces.size() / 3);
  out->clear();
  counts->meshes = 1;
  counts->primitives = 1;
  counts->vertices = nw;
  counts->triangles = nf;
  if (format == "drc") {
    EncodeRequest req;
    req.points = nw;
    req.faces = &f.faces;
    req.attributes.push_back({"POSITION", 3, f.pos.data(), false});
    if (!f.normal.empty()) req.attributes.push_back({"NORMAL", 3, f.normal.data(), false});
    if (!f.uv.empty()) req.attributes.push_back({"TEXCOORD_0", 2, f.uv.data(), false});
    EncodeResult enc;
    Status s = draco_encode(req, opt, &enc);
    if (!s.ok()) return s;
    *out = std::move(enc.bytes);
    counts->vertices = enc.points;
    counts->triangles = enc.faces;
    counts->quantization_collapsed = nf - enc.faces;
    return Status::Ok();
  }
  if (format == "obj") {
    std::ostringstream o;
    o.precision(9);
    o << "# written by IteAS\n";
    for (int64_t i = 0; i < nw; ++i) o << "v " << f.pos[3 * i] << ' ' << f.pos[3 * i + 1] << ' ' << f.pos[3 * i + 2] << '\n';
    for (size_t i = 0; i < f.uv.size() / 2; ++i) o << "vt " << f.uv[2 * i] << ' ' << f.uv[2 * i + 1] << '\n';
    for (size_t i = 0; i < f.normal.size() / 3; ++i)
      o << "vn " << f.normal[3 * i] << ' ' << f.normal[3 * i + 1] << ' ' << f.normal[3 * i + 2] << '\n';
    for (int64_t t = 0; t < nf; ++t) {
      o << 'f';
      for (int k = 0; k < 3; ++k) {
        const int64_t i = f.faces[3 * t + k] + 1;
        o << ' ' << i;
        if (!f.uv.empty() || !f.normal.empty()) o << '/' << (f.uv.empty() ? "" : std::to_string(i));
        if (!f.normal.empty()) o << '/' << i;
      }
      o << '\n';
    }
    const std::string s = o.str();
    out->assign(s.begin(), s.end());
    return Status::Ok();
  }
  if (format == "ply") {
    std::ostringstream h;
    h << "ply\nformat binary_little_endian 1.0\ncomment written by IteAS\nelement vertex " << nw
      << "\nproperty float x\nproperty float y\nproperty float z\n";
    if (!f.normal.empty()) h << "property float nx\nproperty float ny\nproperty float nz\n";
    h << "element face " << nf << "\nproperty list uchar int vertex_indices\nend_header\n";
    const std::string hs = h.str();
    out->assign(hs.begin(), hs.end());
    auto put = [&](const void* p, size_t n) { out->insert(out->end(), static_cast<const uint8_t*>(p), static_cast<const uint8_t*>(p) + n); };
    for (int64_t i = 0; i < nw; ++i) {
      put(&f.pos[3 * i], 12);
      if (!f.normal.empty()) put(&f.normal[3 * i], 12);
    }
    for (int64_t t = 0; t < nf; ++t) {
      const uint8_t three = 3;
      put(&three, 1);
      put(&f.faces[3 * t], 12);
    }
    return Status::Ok();
  }
  return Status::Error(ErrorKind::kUnsupported, "unsupported_format", "unknown output format " + format);
}

}  // namespace iteas
