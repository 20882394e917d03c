// Our mesh as an OpenMesh triangle mesh, for the differential test and the
// benchmark (OpenMesh is a test-and-bench-only reference).
#pragma once

#include <vector>

#include "core/mesh.h"

namespace iteas::test {

template <class OMesh>
void to_openmesh(const Mesh& m, OMesh& om) {
  using Scalar = typename OMesh::Point::value_type;
  std::vector<typename OMesh::VertexHandle> vh;
  vh.reserve(size_t(m.num_vertices()));
  for (int32_t v = 0; v < m.num_vertices(); ++v)
    vh.push_back(om.add_vertex(typename OMesh::Point(Scalar(m.positions[3 * v]), Scalar(m.positions[3 * v + 1]),
                                                     Scalar(m.positions[3 * v + 2]))));
  for (int32_t f = 0; f < m.num_faces(); ++f)
    om.add_face(vh[m.corner_vertex[3 * f]], vh[m.corner_vertex[3 * f + 1]], vh[m.corner_vertex[3 * f + 2]]);
}

}  // namespace iteas::test
