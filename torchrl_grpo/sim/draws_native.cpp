// The draws highway-env's resets and spawns make from the env's numpy Generator, replayed
// in C++ on each world's generator words (gym_state.encode_rng), bit for bit: a batch of
// resets or spawns costs no Python call per world. Each function reads the words of the
// rows in `rows`, writes their draws and the words after them; the other rows keep their
// words and get the "no draw" values the Python replays give them.
//
// Built and loaded by torchrl_grpo/sim/draws_native.py, linked with numpy's libnpyrandom
// (numpy_draws.h).
#include <cstdint>

#include "numpy_draws.h"

namespace {

void copy_words(const int64_t* from, int64_t* to) {
  for (int k = 0; k < 10; ++k) to[k] = from[k];
}

// draw(b, generator) on each row b of `rows`, its words after in `after`; the other rows
// keep their words.
template <class Draw>
void each_row(const int64_t* words, const uint8_t* rows, int64_t batch, int64_t* after,
              Draw draw) {
  for (int64_t b = 0; b < batch; ++b) {
    copy_words(words + 10 * b, after + 10 * b);
    if (!rows[b]) continue;
    highway::NumpyGenerator g(words + 10 * b);
    draw(b, g);
    g.store(after + 10 * b);
  }
}

}  // namespace

// merge-v0's reset (MergeEnv._make_vehicles): per highway car integers(2),
// uniform(-5, 5), uniform(-1, 1). Draws [B, 3 * cars], zero outside `rows`.
extern "C" void merge_draws(const int64_t* words, const uint8_t* rows, int64_t batch,
                            int64_t cars, double* draws, int64_t* after) {
  each_row(words, rows, batch, after, [&](int64_t b, highway::NumpyGenerator& g) {
    double* d = draws + 3 * cars * b;
    for (int64_t k = 0; k < cars; ++k) {
      d[3 * k] = double(g.integers(0, 2));
      d[3 * k + 1] = g.uniform(-5.0, 5.0);
      d[3 * k + 2] = g.uniform(-1.0, 1.0);
    }
  });
}

// roundabout-v0's reset (RoundaboutEnv._make_vehicles): per IDM vehicle normal(),
// normal(), choice(destinations) (the integers(exits) it draws), uniform(low, high).
// Draws [B, 4 * cars], zero outside `rows`.
extern "C" void roundabout_draws(const int64_t* words, const uint8_t* rows, int64_t batch,
                                 int64_t cars, int64_t exits, double low, double high,
                                 double* draws, int64_t* after) {
  each_row(words, rows, batch, after, [&](int64_t b, highway::NumpyGenerator& g) {
    double* d = draws + 4 * cars * b;
    for (int64_t k = 0; k < cars; ++k) {
      d[4 * k] = g.normal();
      d[4 * k + 1] = g.normal();
      d[4 * k + 2] = double(g.integers(0, exits));
      d[4 * k + 3] = g.uniform(low, high);
    }
  });
}

// One intersection-v0 spawn (IntersectionEnv._spawn_vehicle): uniform(), and unless it
// exceeds `probability`, choice(4, 2, replace=False) (the second leg straight across
// when `go_straight`), normal() twice; the words then (`dropped`); then, only if the car
// is spawned, uniform(low, high) and the words after it (`stays`). Draws [B, 6]:
// (uniform, corner, destination, position normal, speed normal, exponent); all 1
// outside `rows` (a uniform of 1 exceeds any probability: no spawn).
extern "C" void spawn_draws(const int64_t* words, const uint8_t* rows, int64_t batch,
                            double probability, int go_straight, double low, double high,
                            double* draws, int64_t* dropped, int64_t* stays) {
  for (int64_t b = 0; b < batch; ++b) {
    double* d = draws + 6 * b;
    copy_words(words + 10 * b, dropped + 10 * b);
    copy_words(words + 10 * b, stays + 10 * b);
    for (int k = 0; k < 6; ++k) d[k] = 1.0;
    if (!rows[b]) continue;
    highway::NumpyGenerator g(words + 10 * b);
    const double u = g.uniform();
    d[0] = u;
    for (int k = 1; k < 6; ++k) d[k] = 0.0;
    const bool spawns = !(u > probability);
    if (spawns) {
      int64_t route[2];
      g.choice_without_replacement(4, 2, route);
      if (go_straight) route[1] = (route[0] + 2) % 4;
      d[1] = double(route[0]);
      d[2] = double(route[1]);
      d[3] = g.normal();
      d[4] = g.normal();
    }
    g.store(dropped + 10 * b);
    if (spawns) d[5] = g.uniform(low, high);
    g.store(stays + 10 * b);
  }
}

// intersection-v0's ego (IntersectionEnv._make_vehicles): integers(1, 4) when the
// config's destination is random (`destination` < 0, else it is the goal), then
// normal(1.0). Goal [B], offset [B]; outside `rows` the config's goal and 0.
extern "C" void ego_draws(const int64_t* words, const uint8_t* rows, int64_t batch,
                          int64_t destination, int64_t* goal, double* offset, int64_t* after) {
  for (int64_t b = 0; b < batch; ++b) {
    goal[b] = destination < 0 ? 0 : destination;
    offset[b] = 0.0;
  }
  each_row(words, rows, batch, after, [&](int64_t b, highway::NumpyGenerator& g) {
    if (destination < 0) goal[b] = g.integers(1, 4);
    offset[b] = g.normal(1.0);
  });
}
