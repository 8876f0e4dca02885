// Deck reading: see deck_reader.hpp.
#include "deck/deck_reader.hpp"

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>

namespace calfit {
namespace {

std::string trim(const std::string& s) {
  std::size_t a = 0, b = s.size();
  while (a < b && std::isspace(static_cast<unsigned char>(s[a]))) ++a;
  while (b > a && std::isspace(static_cast<unsigned char>(s[b - 1]))) --b;
  return s.substr(a, b - a);
}

// Each field is trimmed where it lies and copied once (a mesh deck is mostly data lines: the 22.5k-DOF slice's
// 17k took a third of its parse through the temporaries of substr and trim).
std::vector<std::string> split_commas(const std::string& line) {
  std::vector<std::string> out;
  out.reserve(static_cast<std::size_t>(std::count(line.begin(), line.end(), ',')) + 1);
  const char* text = line.data();
  std::size_t start = 0;
  while (true) {
    const std::size_t comma = line.find(',', start);
    std::size_t a = start, b = comma == std::string::npos ? line.size() : comma;
    while (a < b && std::isspace(static_cast<unsigned char>(text[a]))) ++a;
    while (b > a && std::isspace(static_cast<unsigned char>(text[b - 1]))) --b;
    out.emplace_back(text + a, b - a);
    if (comma == std::string::npos) break;
    start = comma + 1;
  }
  while (!out.empty() && out.back().empty()) out.pop_back();
  return out;
}

std::string collapse_spaces(const std::string& s) {
  std::string out;
  for (char c : s) {
    if (std::isspace(static_cast<unsigned char>(c))) {
      if (!out.empty() && out.back() != ' ') out += ' ';
    } else {
      out += c;
    }
  }
  return trim(out);
}

KeywordBlock parse_keyword_line(const std::string& text, const SourceLocation& where) {
  std::vector<std::string> parts = split_commas(text.substr(1));
  if (parts.empty() || parts[0].empty()) throw DeckError(where, "empty keyword after '*'");
  KeywordBlock block;
  block.name = upper(collapse_spaces(parts[0]));
  block.where = where;
  for (std::size_t i = 1; i < parts.size(); ++i) {
    if (parts[i].empty()) throw DeckError(where, "empty parameter in keyword line (two commas in a row?)");
    Parameter p;
    const std::size_t eq = parts[i].find('=');
    if (eq == std::string::npos) {
      p.name = upper(collapse_spaces(parts[i]));
    } else {
      p.name = upper(collapse_spaces(parts[i].substr(0, eq)));
      p.value = trim(parts[i].substr(eq + 1));
      p.has_value = true;
      if (p.value.empty()) throw DeckError(where, "parameter " + p.name + "= has no value");
    }
    block.parameters.push_back(p);
  }
  return block;
}

// A deck is text: a control byte (other than tab) means a binary or corrupted file, and quoting the line
// would send that byte to the user's terminal.
void reject_control_bytes(const std::string& raw, const SourceLocation& where) {
  for (std::size_t i = 0; i < raw.size(); ++i) {
    const auto byte = static_cast<unsigned char>(raw[i]);
    if ((byte < 0x20 && byte != '\t') || byte == 0x7f) {
      static const char* hex = "0123456789abcdef";
      throw DeckError(where, std::string("byte 0x") + hex[byte >> 4] + hex[byte & 15] + " at column " +
                                 std::to_string(i + 1) + " is not text: is this file a deck?");
    }
  }
}

class Reader {
public:
  std::vector<KeywordBlock> blocks;

  void read_file(const std::string& path, const SourceLocation* included_from) {
    namespace fs = std::filesystem;
    std::error_code ec;
    const std::string canonical = fs::weakly_canonical(path, ec).string();
    if (std::find(stack_.begin(), stack_.end(), canonical) != stack_.end())
      throw DeckError(*included_from, "*INCLUDE cycle: " + path + " includes itself (directly or indirectly)");
    std::ifstream in(path);
    if (!in) {
      if (included_from)
        throw DeckError(*included_from, "cannot open included file " + path + ": check the INPUT= path");
      throw DeckError({path, 0}, "cannot open the deck file");
    }
    stack_.push_back(canonical);
    std::string raw;
    int line_no = 0;
    std::string pending_keyword;  // keyword line continued with a trailing comma
    SourceLocation pending_where;
    while (std::getline(in, raw)) {
      ++line_no;
      if (!raw.empty() && raw.back() == '\r') raw.pop_back();
      const SourceLocation where{path, line_no};
      reject_control_bytes(raw, where);
      const std::string line = trim(raw);
      if (!pending_keyword.empty()) {
        if (line.rfind("**", 0) == 0) continue;
        pending_keyword += line;
        if (!line.empty() && line.back() == ',') continue;
        handle_keyword(pending_keyword, pending_where, path);
        pending_keyword.clear();
        continue;
      }
      if (line.empty() || line.rfind("**", 0) == 0) continue;
      if (line[0] == '*') {
        if (line.back() == ',') {
          pending_keyword = line;
          pending_where = where;
          continue;
        }
        handle_keyword(line, where, path);
        continue;
      }
      if (blocks.empty() || in_include_keyword_) throw DeckError(where, "data line before any keyword");
      blocks.back().data.push_back({where, split_commas(line)});
    }
    if (!pending_keyword.empty()) throw DeckError(pending_where, "keyword line ends with ',' but the file ends");
    stack_.pop_back();
  }

private:
  std::vector<std::string> stack_;
  bool in_include_keyword_ = false;

  void handle_keyword(const std::string& line, const SourceLocation& where, const std::string& path) {
    KeywordBlock block = parse_keyword_line(line, where);
    if (block.name == "INCLUDE") {
      block.allow_only({"INPUT"});
      std::filesystem::path target = block.required("INPUT");
      if (target.is_relative()) target = std::filesystem::path(path).parent_path() / target;
      in_include_keyword_ = false;
      read_file(target.string(), &where);
      in_include_keyword_ = true;  // data lines right after *INCLUDE belong to no keyword
      return;
    }
    in_include_keyword_ = false;
    blocks.push_back(std::move(block));
  }
};

}  // namespace

std::string upper(std::string text) {
  for (char& c : text) c = static_cast<char>(std::toupper(static_cast<unsigned char>(c)));
  return text;
}

void KeywordBlock::allow_only(const std::vector<std::string>& allowed) const {
  for (const Parameter& p : parameters) {
    if (std::find(allowed.begin(), allowed.end(), p.name) != allowed.end()) continue;
    std::string list;
    for (const std::string& a : allowed) list += (list.empty() ? "" : ", ") + a;
    throw DeckError(where, "unknown parameter " + p.name + " on *" + name +
                               (allowed.empty() ? " (it takes none)" : " (allowed: " + list + ")"));
  }
}

const Parameter* KeywordBlock::find(const std::string& key) const {
  for (const Parameter& p : parameters)
    if (p.name == key) return &p;
  return nullptr;
}

std::optional<std::string> KeywordBlock::value(const std::string& key) const {
  const Parameter* p = find(key);
  if (!p) return std::nullopt;
  if (!p->has_value) throw DeckError(where, "parameter " + key + " of *" + name + " needs a value: " + key + "=...");
  return p->value;
}

std::string KeywordBlock::required(const std::string& key) const {
  const std::optional<std::string> v = value(key);
  if (!v) throw DeckError(where, "*" + name + " needs the parameter " + key + "=");
  return *v;
}

std::vector<KeywordBlock> read_deck(const std::string& path) {
  Reader reader;
  reader.read_file(path, nullptr);
  return std::move(reader.blocks);
}

std::string printable(const std::string& text) {
  static const char* hex = "0123456789abcdef";
  std::string out;
  out.reserve(text.size());
  for (char c : text) {
    const auto byte = static_cast<unsigned char>(c);
    if (byte >= 0x20 && byte < 0x7f) {
      out += c;
    } else {
      out += "\\x";
      out += hex[byte >> 4];
      out += hex[byte & 15];
    }
  }
  return out;
}

double to_double(const std::string& text, const SourceLocation& where, const std::string& what) {
  if (text.empty()) throw DeckError(where, what + " is missing");
  std::string fortran;  // Fortran exponents, as CalculiX accepts: 1.5d3 is read as 1.5e3
  if (text.find_first_of("dD") != std::string::npos) {
    fortran = text;
    for (char& c : fortran)
      if (c == 'd' || c == 'D') c = 'e';
  }
  const std::string& t = fortran.empty() ? text : fortran;
  errno = 0;
  char* end = nullptr;
  const double v = std::strtod(t.c_str(), &end);
  if (end != t.c_str() + t.size() || errno == ERANGE || !std::isfinite(v))
    throw DeckError(where, what + " is not a number: '" + text + "'");
  return v;
}

bool looks_like_int(const std::string& text) {
  if (text.empty()) return false;
  std::size_t i = (text[0] == '-' || text[0] == '+') ? 1 : 0;
  if (i == text.size()) return false;
  for (; i < text.size(); ++i)
    if (!std::isdigit(static_cast<unsigned char>(text[i]))) return false;
  return true;
}

int to_int(const std::string& text, const SourceLocation& where, const std::string& what) {
  if (text.empty()) throw DeckError(where, what + " is missing");
  if (!looks_like_int(text)) throw DeckError(where, what + " is not an integer: '" + text + "'");
  errno = 0;
  const long v = std::strtol(text.c_str(), nullptr, 10);
  if (errno == ERANGE || v > 2147483647L || v < -2147483647L) throw DeckError(where, what + " is out of range: " + text);
  return static_cast<int>(v);
}

}  // namespace calfit
