// numpy's Generator draws on a world's PCG64 state, through numpy's own C distributions.
//
// numpy ships the C code behind Generator's methods as a static library (libnpyrandom,
// with numpy/random/bitgen.h); this header hands it our Pcg64 (pcg64.h) as a bit
// generator, so that normal() is numpy's ziggurat itself and choice() the same calls in
// the same order as Generator.choice, with no Python call per world. The library is
// linked by torchrl_grpo/sim/draws_native.py; the tests compare every draw and every
// word with numpy's.
#pragma once

#include <cstdint>
#include <vector>

#include "numpy/random/bitgen.h"
#include "pcg64.h"

// The few functions of numpy/random/distributions.h used here (that header needs Python.h).
extern "C" {
double random_normal(bitgen_t* bitgen_state, double loc, double scale);
uint64_t random_bounded_uint64(bitgen_t* bitgen_state, uint64_t off, uint64_t rng, uint64_t mask,
                               bool use_masked);
void random_bounded_uint64_fill(bitgen_t* bitgen_state, uint64_t off, uint64_t rng, intptr_t cnt,
                                bool use_masked, uint64_t* out);
}

namespace highway {

// One world's numpy Generator: its PCG64 state (10 words in, 10 words out) as a bitgen_t.
class NumpyGenerator {
 public:
  explicit NumpyGenerator(const int64_t* words) : pcg_(words) {
    bitgen_ = bitgen_t{&pcg_, next64, next32, next_double, next64};
  }
  // The bit generator points at this object's own state: no copies.
  NumpyGenerator(const NumpyGenerator&) = delete;
  NumpyGenerator& operator=(const NumpyGenerator&) = delete;

  void store(int64_t* words) const { pcg_.store(words); }

  // Generator.uniform(low, high): random_uniform's low + (high - low) * next_double.
  double uniform(double low = 0.0, double high = 1.0) { return pcg_.uniform(low, high); }

  // Generator.normal(loc, scale): numpy's ziggurat.
  double normal(double loc = 0.0, double scale = 1.0) {
    return random_normal(&bitgen_, loc, scale);
  }

  // Generator.integers(low, high) of int64, high excluded (high > low).
  int64_t integers(int64_t low, int64_t high) {
    uint64_t out = 0;
    random_bounded_uint64_fill(&bitgen_, uint64_t(low), uint64_t(high - low - 1), 1, false, &out);
    return int64_t(out);
  }

  // Generator.choice(population, size, replace=False) of indices, for a population of at
  // most 10,000 (Floyd's algorithm on a hash set, then the shuffle of the sample). `out`
  // holds `size` indices.
  void choice_without_replacement(int64_t population, int64_t size, int64_t* out) {
    // The hash set's size: the smallest power of two above 1.2 * size, as numpy's.
    uint64_t mask = uint64_t(1.2 * double(size));
    for (int shift = 1; shift < 64; shift <<= 1) mask |= mask >> shift;
    constexpr uint64_t kEmpty = ~uint64_t(0);
    std::vector<uint64_t> set(mask + 1, kEmpty);
    for (int64_t j = population - size; j < population; ++j) {
      const uint64_t val = random_bounded_uint64(&bitgen_, 0, uint64_t(j), 0, false);
      uint64_t loc = val & mask;
      while (set[loc] != kEmpty && set[loc] != val) loc = (loc + 1) & mask;
      if (set[loc] == kEmpty) {  // val not drawn before: keep it
        set[loc] = val;
        out[j - population + size] = int64_t(val);
      } else {  // drawn before: j instead
        loc = uint64_t(j) & mask;
        while (set[loc] != kEmpty) loc = (loc + 1) & mask;
        set[loc] = uint64_t(j);
        out[j - population + size] = j;
      }
    }
    for (int64_t i = size - 1; i >= 1; --i) {  // the sample's Fisher-Yates shuffle
      const int64_t j = int64_t(random_bounded_uint64(&bitgen_, 0, uint64_t(i), 0, false));
      const int64_t swap = out[j];
      out[j] = out[i];
      out[i] = swap;
    }
  }

 private:
  static uint64_t next64(void* s) { return static_cast<Pcg64*>(s)->next64(); }
  static uint32_t next32(void* s) { return static_cast<Pcg64*>(s)->next32(); }
  static double next_double(void* s) { return static_cast<Pcg64*>(s)->next_double(); }

  Pcg64 pcg_;
  bitgen_t bitgen_;
};

}  // namespace highway
