// Reads an Abaqus/CalculiX-style input deck into keyword blocks, following
// *INCLUDE, keeping the file and line of every keyword and data line so that each
// later error can name them. Syntax: a line starting with '*' (not '**') is a
// keyword line "*NAME, PARAM=VALUE, FLAG"; a keyword line ending with ',' continues
// on the next line; '**' lines are comments; other non-blank lines are data lines,
// comma separated.
#pragma once

#include "model/source_location.hpp"

#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

namespace calfit {

// Error in the user's input: reported as "FILE:LINE: message", exit code 2.
std::string printable(const std::string& text);

class DeckError : public std::runtime_error {
public:
  // The message is kept on one printable line: bytes outside printable ASCII are written as \xNN.
  DeckError(const SourceLocation& where, const std::string& message)
      : std::runtime_error(where.file + ":" + std::to_string(where.line) + ": " + printable(message)), where_(where) {}
  const SourceLocation& where() const { return where_; }

private:
  SourceLocation where_;
};

struct DataLine {
  SourceLocation where;
  std::vector<std::string> fields;  // trimmed; trailing empty fields removed
};

struct Parameter {
  std::string name;   // upper case
  std::string value;  // as written (empty for a flag)
  bool has_value = false;
};

struct KeywordBlock {
  std::string name;  // upper case, single spaces: "SOLID SECTION"
  std::vector<Parameter> parameters;
  SourceLocation where;
  std::vector<DataLine> data;

  // Throws DeckError for any parameter not in `allowed` (upper case names).
  void allow_only(const std::vector<std::string>& allowed) const;
  const Parameter* find(const std::string& key) const;
  std::optional<std::string> value(const std::string& key) const;
  std::string required(const std::string& key) const;  // throws when missing or empty
  bool flag(const std::string& key) const { return find(key) != nullptr; }
};

std::vector<KeywordBlock> read_deck(const std::string& path);

// Field conversions that name the line and the field on failure.
double to_double(const std::string& text, const SourceLocation& where, const std::string& what);
int to_int(const std::string& text, const SourceLocation& where, const std::string& what);
bool looks_like_int(const std::string& text);
std::string upper(std::string text);

}  // namespace calfit
