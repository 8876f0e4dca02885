// The deck parser's entry: the deck read into keyword blocks (deck_reader.hpp), each keyword turned into its part
// of the Model by its handler (model_builder.hpp, keywords_*.cpp) and the whole model checked.
#pragma once

#include "deck/deck_reader.hpp"
#include "model/model.hpp"

#include <string>

namespace calfit {

// Parses the deck at `path` and checks the mesh; throws DeckError on bad input.
Model build_model(const std::string& path);

}  // namespace calfit
