// Minimal assertion helpers for the C++ unit tests (run by ctest): each failed check
// prints where and why; main returns the failure count and prints "N passed, N failed".
#pragma once

#include <cmath>
#include <iostream>
#include <string>

namespace calfit::testing {

struct Tally {
  int passed = 0, failed = 0;
  void check(bool ok, const std::string& what, const char* file, int line) {
    if (ok) {
      ++passed;
      return;
    }
    ++failed;
    std::cerr << file << ":" << line << ": FAILED: " << what << '\n';
  }
  int finish() const {
    std::cout << passed << " passed, " << failed << " failed\n";
    return failed == 0 ? 0 : 1;
  }
};

inline Tally& tally() {
  static Tally t;
  return t;
}

}  // namespace calfit::testing

#define CHECK(cond) ::calfit::testing::tally().check((cond), #cond, __FILE__, __LINE__)
#define CHECK_NEAR(a, b, tol)                                                                          \
  ::calfit::testing::tally().check(std::abs((a) - (b)) <= (tol),                                       \
                                   std::string(#a " ~ " #b ": ") + std::to_string(a) + " vs " +        \
                                       std::to_string(b) + " (tol " + std::to_string(tol) + ")",        \
                                   __FILE__, __LINE__)
