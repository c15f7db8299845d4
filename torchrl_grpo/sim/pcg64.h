// numpy's PCG64 bit generator and the Generator draws merge-v0's reset makes, bit for bit.
//
// highway-env draws a merge reset from the env's numpy Generator (PCG64). The tensor
// simulator carries each world's generator state as 10 int64 words (gym_state.encode_rng:
// the 128-bit state and increment in 32-bit words, then has_uint32 and uinteger) and
// replays those draws; this header replays them without numpy, so that a batch of resets
// costs no Python call per world. The tests compare every draw and every word with numpy's.
#pragma once

#include <cstdint>

namespace highway {

using u128 = unsigned __int128;

struct Pcg64 {
  u128 state, inc;
  int64_t has_uint32;
  uint32_t uinteger;

  explicit Pcg64(const int64_t* w) {
    state = inc = 0;
    for (int j = 3; j >= 0; --j) {
      state = (state << 32) | u128(uint32_t(w[j]));
      inc = (inc << 32) | u128(uint32_t(w[4 + j]));
    }
    has_uint32 = w[8];
    uinteger = uint32_t(w[9]);
  }

  void store(int64_t* w) const {
    for (int j = 0; j < 4; ++j) {
      w[j] = int64_t(uint32_t(state >> (32 * j)));
      w[4 + j] = int64_t(uint32_t(inc >> (32 * j)));
    }
    w[8] = has_uint32;
    w[9] = int64_t(uinteger);
  }

  // pcg_setseq_128_xsl_rr_64: step, then the rotated xor of the new state's halves.
  uint64_t next64() {
    const u128 mult = (u128(0x2360ED051FC65DA4ULL) << 64) | u128(0x4385DF649FCCF645ULL);
    state = state * mult + inc;
    const uint64_t x = uint64_t(state >> 64) ^ uint64_t(state);
    const unsigned rot = unsigned(state >> 122);
    return (x >> rot) | (x << ((64 - rot) & 63));
  }

  // The bit generator's 32-bit draw keeps the upper half of a 64-bit one for next time.
  uint32_t next32() {
    if (has_uint32) {
      has_uint32 = 0;
      return uinteger;
    }
    const uint64_t next = next64();
    has_uint32 = 1;
    uinteger = uint32_t(next >> 32);
    return uint32_t(next);
  }

  double next_double() { return double(next64() >> 11) * (1.0 / 9007199254740992.0); }

  // Generator.integers(n) for 1 <= n < 2^32 (Lemire's method on 32-bit draws).
  int64_t integers(uint32_t n) {
    if (n == 1) return 0;
    uint64_t m = uint64_t(next32()) * n;
    uint32_t leftover = uint32_t(m);
    if (leftover < n) {
      const uint32_t threshold = uint32_t(-n) % n;  // (2^32 - n) mod n
      while (leftover < threshold) {
        m = uint64_t(next32()) * n;
        leftover = uint32_t(m);
      }
    }
    return int64_t(m >> 32);
  }

  // Generator.uniform(low, high).
  double uniform(double low, double high) { return low + (high - low) * next_double(); }
};

}  // namespace highway
