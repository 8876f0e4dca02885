// Result writers: see writers.hpp.
#include "output/writers.hpp"

#include <cmath>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <sstream>
#include <stdexcept>

namespace calfit {
namespace {

// Writes through a temporary file renamed into place once complete.
template <typename Fill>
void write_atomically(const std::string& path, Fill fill, bool binary = false) {
  const std::string temporary = path + ".part";
  {
    std::ofstream out(temporary, binary ? std::ios::binary : std::ios::out);
    if (!out) throw std::runtime_error("cannot write " + temporary);
    fill(out);
    out.flush();
    if (!out) throw std::runtime_error("error while writing " + temporary + " (disk full?)");
  }
  std::filesystem::rename(temporary, path);
}

std::string json_string(const std::string& s) {
  std::ostringstream out;
  out << '"';
  for (char c : s) {
    switch (c) {
      case '"': out << "\\\""; break;
      case '\\': out << "\\\\"; break;
      case '\n': out << "\\n"; break;
      case '\t': out << "\\t"; break;
      default:
        if (static_cast<unsigned char>(c) < 0x20) {
          out << "\\u" << std::hex << std::setw(4) << std::setfill('0') << static_cast<int>(c) << std::dec;
        } else {
          out << c;
        }
    }
  }
  out << '"';
  return out.str();
}

std::string json_number(double v) {
  if (!std::isfinite(v)) return "null";
  std::ostringstream out;
  out << std::setprecision(17) << v;
  return out.str();
}

constexpr int kVtkTriangle = 5, kVtkQuadraticTriangle = 22;

// Base64 of the concatenation of two byte ranges (a VTK header and its values) without copying them into one
// string first, into a buffer sized once: the copy and character by character appends took a third of the time
// of writing the 22.5k-DOF calf's VTU.
std::string base64(const unsigned char* head, std::size_t head_size, const unsigned char* tail, std::size_t tail_size) {
  static const char* table = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
  const std::size_t size = head_size + tail_size;
  auto byte = [&](std::size_t k) -> unsigned { return k < head_size ? head[k] : tail[k - head_size]; };
  std::string out((size + 2) / 3 * 4, '=');
  char* o = out.data();
  std::size_t i = 0;
  for (; i + 2 < size; i += 3, o += 4) {
    unsigned v;
    if (i >= head_size) {
      const unsigned char* t = tail + (i - head_size);
      v = (static_cast<unsigned>(t[0]) << 16) | (static_cast<unsigned>(t[1]) << 8) | t[2];
    } else {  // a group that touches the header
      v = (byte(i) << 16) | (byte(i + 1) << 8) | byte(i + 2);
    }
    o[0] = table[(v >> 18) & 63];
    o[1] = table[(v >> 12) & 63];
    o[2] = table[(v >> 6) & 63];
    o[3] = table[v & 63];
  }
  if (i < size) {  // one or two bytes left: padded with '='
    const bool two = i + 1 < size;
    const unsigned v = (byte(i) << 16) | (two ? byte(i + 1) << 8 : 0u);
    o[0] = table[(v >> 18) & 63];
    o[1] = table[(v >> 12) & 63];
    if (two) o[2] = table[(v >> 6) & 63];
  }
  return out;
}

// Field names come from the deck (sensitivity parameters): escape what XML reserves.
std::string xml_attribute(const std::string& text) {
  std::string out;
  for (char c : text) {
    switch (c) {
      case '&': out += "&amp;"; break;
      case '<': out += "&lt;"; break;
      case '>': out += "&gt;"; break;
      case '"': out += "&quot;"; break;
      default: out += c;
    }
  }
  return out;
}

// One VTK XML DataArray in "binary" format: base64 of a UInt64 byte count followed by
// the little-endian values (the layout ParaView and meshio read).
template <typename T>
void data_array(std::ostream& out, const char* vtk_type, const char* name, int components, const std::vector<T>& values) {
  const std::uint64_t size = values.size() * sizeof(T);
  out << "        <DataArray type=\"" << vtk_type << "\"";
  if (name) out << " Name=\"" << xml_attribute(name) << "\"";
  out << " NumberOfComponents=\"" << components << "\" format=\"binary\">\n"
      << base64(reinterpret_cast<const unsigned char*>(&size), sizeof(size),
                reinterpret_cast<const unsigned char*>(values.data()), size)
      << "\n        </DataArray>\n";
}

std::vector<double> voigt6(const Mat3& s) { return {s(0, 0), s(1, 1), s(2, 2), s(0, 1), s(1, 2), s(0, 2)}; }

}  // namespace

void write_vtu(const std::string& path, const Model& model, const FieldOutput& fields) {
  const std::size_t n_nodes = model.coordinates.size(), n_elements = model.elements.size();
  std::vector<double> points, displacement, reaction, point_stress(6 * n_nodes, 0.0), point_pressure(n_nodes, 0.0),
      laplace;
  std::vector<double> count(n_nodes, 0.0), cell_stress, cell_pressure, cell_J, material;
  const std::vector<double> contact_pressure(fields.contact_pressure.data(),
                                             fields.contact_pressure.data() + fields.contact_pressure.size());
  const std::vector<double> contact_shear(fields.contact_shear.data(), fields.contact_shear.data() + fields.contact_shear.size());
  const std::vector<double> contact_status(fields.contact_status.data(),
                                           fields.contact_status.data() + fields.contact_status.size());
  const std::vector<double> contact_slip(fields.contact_slip.data(),
                                         fields.contact_slip.data() + fields.contact_slip.size());
  std::vector<std::int64_t> connectivity, offsets;
  std::vector<std::uint8_t> types;
  for (std::size_t n = 0; n < n_nodes; ++n) {
    points.insert(points.end(), {model.coordinates[n].x(), model.coordinates[n].y(), 0.0});
    displacement.insert(displacement.end(), {fields.displacement[2 * n], fields.displacement[2 * n + 1], 0.0});
    reaction.insert(reaction.end(), {fields.reaction[2 * n], fields.reaction[2 * n + 1], 0.0});
    laplace.push_back(fields.laplace_pressure[static_cast<Eigen::Index>(n)]);
  }
  for (std::size_t e = 0; e < n_elements; ++e) {
    const ElementDef& element = model.elements[e];
    const ElementState& s = fields.element_states[e];
    const std::vector<double> v = voigt6(s.cauchy);
    const double pressure = -s.cauchy.trace() / 3.0;
    cell_stress.insert(cell_stress.end(), v.begin(), v.end());
    cell_pressure.push_back(pressure);
    cell_J.push_back(s.J);
    material.push_back(model.sections[element.section].material + 1);
    connectivity.insert(connectivity.end(), element.nodes.begin(), element.nodes.end());
    offsets.push_back(static_cast<std::int64_t>(connectivity.size()));
    types.push_back(element.shape == ElementShape::T3 ? kVtkTriangle : kVtkQuadraticTriangle);
    for (int node : element.nodes) {
      for (int k = 0; k < 6; ++k) point_stress[6 * node + k] += v[k];
      point_pressure[node] += pressure;
      count[node] += 1.0;
    }
  }
  for (std::size_t n = 0; n < n_nodes; ++n) {
    if (count[n] == 0.0) continue;
    for (int k = 0; k < 6; ++k) point_stress[6 * n + k] /= count[n];
    point_pressure[n] /= count[n];
  }

  write_atomically(path, [&](std::ostream& out) {
    out << "<?xml version=\"1.0\"?>\n<VTKFile type=\"UnstructuredGrid\" version=\"1.0\" byte_order=\"LittleEndian\""
        << " header_type=\"UInt64\">\n  <UnstructuredGrid>\n    <Piece NumberOfPoints=\"" << n_nodes
        << "\" NumberOfCells=\"" << n_elements << "\">\n      <Points>\n";
    data_array(out, "Float64", nullptr, 3, points);
    out << "      </Points>\n      <Cells>\n";
    data_array(out, "Int64", "connectivity", 1, connectivity);
    data_array(out, "Int64", "offsets", 1, offsets);
    data_array(out, "UInt8", "types", 1, types);
    out << "      </Cells>\n      <PointData>\n";
    data_array(out, "Float64", "displacement", 3, displacement);
    data_array(out, "Float64", "reaction", 3, reaction);
    data_array(out, "Float64", "cauchy_stress", 6, point_stress);
    data_array(out, "Float64", "pressure", 1, point_pressure);
    data_array(out, "Float64", "laplace_pressure", 1, laplace);
    data_array(out, "Float64", "contact_pressure", 1, contact_pressure);
    data_array(out, "Float64", "contact_shear", 1, contact_shear);
    data_array(out, "Float64", "contact_status", 1, contact_status);
    data_array(out, "Float64", "contact_slip", 1, contact_slip);
    for (const auto& [name, field] : fields.point_vectors) {
      std::vector<double> values;
      values.reserve(3 * n_nodes);
      for (std::size_t n = 0; n < n_nodes; ++n) values.insert(values.end(), {field[2 * n], field[2 * n + 1], 0.0});
      data_array(out, "Float64", name.c_str(), 3, values);
    }
    out << "      </PointData>\n      <CellData>\n";
    data_array(out, "Float64", "cauchy_stress", 6, cell_stress);
    data_array(out, "Float64", "pressure", 1, cell_pressure);
    data_array(out, "Float64", "J", 1, cell_J);
    data_array(out, "Float64", "material_id", 1, material);
    for (const auto& [name, field] : fields.cell_scalars)
      data_array(out, "Float64", name.c_str(), 1, std::vector<double>(field.data(), field.data() + field.size()));
    out << "      </CellData>\n    </Piece>\n  </UnstructuredGrid>\n</VTKFile>\n";
  }, true);
}

void write_displacement_table(const std::string& path, const Model& model, const Eigen::VectorXd& u) {
  const std::size_t n = model.coordinates.size();
  // NPY format 1.0: magic, version, little-endian header length, a Python dict
  // literal padded with spaces to a multiple of 64 bytes, then the raw array.
  std::string header = "{'descr': '<f8', 'fortran_order': False, 'shape': (" + std::to_string(n) + ", 5), }";
  const std::size_t total = 10 + header.size() + 1;
  header.append((64 - total % 64) % 64, ' ');
  header += '\n';
  std::vector<double> table;
  table.reserve(5 * n);
  for (std::size_t i = 0; i < n; ++i)
    table.insert(table.end(), {static_cast<double>(model.node_ids[i]), model.coordinates[i].x(),
                               model.coordinates[i].y(), u[2 * i], u[2 * i + 1]});
  write_atomically(
      path,
      [&](std::ostream& out) {
        const unsigned short length = static_cast<unsigned short>(header.size());
        out.write("\x93NUMPY\x01\x00", 8);
        const char length_bytes[2] = {static_cast<char>(length & 0xff), static_cast<char>(length >> 8)};
        out.write(length_bytes, 2);
        out.write(header.data(), static_cast<std::streamsize>(header.size()));
        out.write(reinterpret_cast<const char*>(table.data()), static_cast<std::streamsize>(table.size() * sizeof(double)));
      },
      true);
}

void write_summary(const std::string& path, const RunSummary& s) {
  write_atomically(path, [&](std::ostream& out) {
    out << "{\n  \"deck\": " << json_string(s.deck) << ",\n  \"status\": " << json_string(s.status)
        << ",\n  \"converged\": " << (s.status == "converged" ? "true" : "false") << ",\n  \"exit_code\": " << s.exit_code
        << ",\n  \"message\": " << json_string(s.message) << ",\n  \"wall_time_s\": " << json_number(s.wall_time_s)
        << ",\n  \"time_s\": {\"parse\": " << json_number(s.parse_s) << ", \"assembly\": "
        << json_number(s.timings.assembly_s) << ", \"factorization\": " << json_number(s.timings.factorization_s)
        << ", \"output\": " << json_number(s.output_s) << ", \"sensitivity\": " << json_number(s.sensitivity_s) << "}"
        << ",\n  \"n_nodes\": " << s.n_nodes << ",\n  \"n_elements\": " << s.n_elements << ",\n  \"n_dof\": " << s.n_dof
        << ",\n  \"n_free_dof\": " << s.n_free_dof << ",\n  \"threads\": " << s.threads
        << ",\n  \"linear_solver\": " << json_string(s.linear_solver) << ",\n  \"linear_solves\": {\"factorized\": "
        << s.timings.factorizations << ", \"reused\": " << s.timings.reused_factorizations
        << ", \"gmres_steps\": " << s.timings.krylov_steps << "}"
        << ",\n  \"sensitivities\": [";
    for (std::size_t k = 0; k < s.sensitivities.size(); ++k) {
      const SensitivitySummary& p = s.sensitivities[k];
      out << (k ? "," : "") << "\n    {\"index\": " << p.index << ", \"name\": " << json_string(p.name)
          << ", \"value\": " << json_number(p.value) << ", \"file\": " << json_string(p.file)
          << ", \"max_abs_du\": " << json_number(p.max_abs_du) << "}";
    }
    out << (s.sensitivities.empty() ? "]" : "\n  ]") << ",\n  \"steps\": [";
    for (std::size_t k = 0; k < s.steps.size(); ++k) {
      const StepResult& r = s.steps[k].result;
      out << (k ? "," : "") << "\n    {\"step\": " << k + 1 << ", \"status\": "
          << json_string(r.converged ? "converged" : "not_converged") << ", \"message\": " << json_string(r.message)
          << ", \"time_reached\": " << json_number(r.time_reached) << ", \"n_increments\": " << r.increments
          << ", \"n_cutbacks\": " << r.cutbacks << ", \"newton_iterations\": " << r.newton_iterations
          << ", \"vtu\": " << json_string(s.steps[k].vtu) << ", \"table\": " << json_string(s.steps[k].table)
          << ",\n     \"increments\": [";
      for (std::size_t i = 0; i < r.records.size(); ++i) {
        const IncrementRecord& rec = r.records[i];
        out << (i ? "," : "") << "\n       {\"time\": " << json_number(rec.time) << ", \"dt\": " << json_number(rec.dt)
            << ", \"converged\": " << (rec.converged ? "true" : "false") << ", \"note\": " << json_string(rec.note)
            << ", \"residual_norms\": [";
        for (std::size_t j = 0; j < rec.residual_norms.size(); ++j)
          out << (j ? ", " : "") << json_number(rec.residual_norms[j]);
        out << "]}";
      }
      out << "]}";
    }
    out << "\n  ]\n}\n";
  });
}

}  // namespace calfit
