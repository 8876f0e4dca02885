// Where a model item was read: the deck file and the line of its keyword or data line. Each item of the Model
// keeps its own, so that a later error (a check of the whole model, the solver's) names the line that caused it.
#pragma once

#include <string>

namespace calfit {

struct SourceLocation {
  std::string file;
  int line = 0;
};

}  // namespace calfit
