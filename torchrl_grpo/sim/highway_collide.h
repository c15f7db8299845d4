// Road.step's collision pass in C++, as torchrl_grpo/sim/collision.py computes it.
#pragma once
#include "highway_native.h"

namespace highway {

// utils.are_polygons_intersecting on the rectangles of vehicles a and b (b of size
// b_length x b_width: an obstacle's may differ), a's swept by the pair's relative
// displacement over dt: (intersecting, will intersect, translation).
template <class T>
void separating_axes(const Params& p, const World<T>& w, int a, int b, bool& hit, bool& will,
                     T& tx, T& ty, double b_length, double b_width) {
  const T dt = T(p.dt);
  const T hl[2] = {T(p.length / 2), T(b_length / 2)}, hw[2] = {T(p.width / 2), T(b_width / 2)};
  T cx[2][4], cy[2][4], c[2], s[2];
  const int cars[2] = {a, b};
  for (int k = 0; k < 2; ++k) {
    int v = cars[k];
    const T px[4] = {-hl[k], -hl[k], hl[k], hl[k]}, py[4] = {-hw[k], hw[k], hw[k], -hw[k]};
    c[k] = std::cos(w.h[v]), s[k] = std::sin(w.h[v]);
    for (int q = 0; q < 4; ++q) {
      cx[k][q] = (c[k] * px[q] + (-s[k]) * py[q]) + w.x[v];
      cy[k][q] = (s[k] * px[q] + c[k] * py[q]) + w.y[v];
    }
  }
  T dx = (w.v[a] * c[0]) * dt - (w.v[b] * c[1]) * dt;
  T dy = (w.v[a] * s[0]) * dt - (w.v[b] * s[1]) * dt;
  hit = will = true;
  T best = 0, bx = 0, by = 0;
  for (int e = 0; e < 8; ++e) {  // a's 4 edges, then b's
    int k = e / 4, q = e % 4, r = (q + 1) % 4;
    T nx = -cy[k][r] + cy[k][q], ny = cx[k][r] - cx[k][q];
    T norm = std::sqrt(nx * nx + ny * ny);
    nx = nx / norm, ny = ny / norm;
    T lo[2], hi[2];
    for (int m = 0; m < 2; ++m) {
      lo[m] = hi[m] = cx[m][0] * nx + cy[m][0] * ny;
      for (int u = 1; u < 4; ++u) {
        T proj = cx[m][u] * nx + cy[m][u] * ny;
        lo[m] = std::min(lo[m], proj), hi[m] = std::max(hi[m], proj);
      }
    }
    if ((lo[0] < lo[1] ? lo[1] - hi[0] : lo[0] - hi[1]) > 0) hit = false;
    T vp = nx * dx + ny * dy;
    T lo_a = vp < 0 ? lo[0] + vp : lo[0], hi_a = vp < 0 ? hi[0] : hi[0] + vp;
    T d = lo_a < lo[1] ? lo[1] - hi_a : lo_a - hi[1];
    if (d > 0) will = false;
    if (e == 0 || std::fabs(d) < best) best = std::fabs(d), bx = nx, by = ny;
  }
  // Centre difference: the mean of 4 corners, summed in order as numpy reduces them.
  T ca_x = ((cx[0][0] + cx[0][1] + cx[0][2]) + cx[0][3]) / T(4);
  T cb_x = ((cx[1][0] + cx[1][1] + cx[1][2]) + cx[1][3]) / T(4);
  T ca_y = ((cy[0][0] + cy[0][1] + cy[0][2]) + cy[0][3]) / T(4);
  T cb_y = ((cy[1][0] + cy[1][1] + cy[1][2]) + cy[1][3]) / T(4);
  T sign = (ca_x - cb_x) * bx + (ca_y - cb_y) * by > 0 ? T(1) : T(-1);
  tx = best * (sign * bx), ty = best * (sign * by);
}

// The prefilter: farther apart than the mean diagonal plus i's travel over dt.
template <class T>
bool near(const Params& p, const World<T>& w, int i, int j) {
  double diagonal = std::sqrt(p.length * p.length + p.width * p.width);
  T reach = T((diagonal + diagonal) / 2) + w.v[i] * T(p.dt);
  T dx = w.x[j] - w.x[i], dy = w.y[j] - w.y[i];
  return !(std::sqrt(dx * dx + dy * dy) > reach);
}

// handle_collisions over pairs i < j in road order where either vehicle checks (only
// the ego's pairs in highway-fast-v0): both crash when the rectangles intersect; a
// predicted overlap is a pending impact of half the translation each, and a later
// pair's impact overwrites an earlier one's.
template <class T>
void collide(const Params& p, World<T>& w) {
  const bool all = p.others_check_collisions != 0;
  for (int i = 0; i < (all ? w.n : 1); ++i) {
    if (!w.present[i]) continue;
    for (int j = i + 1; j < w.n; ++j) {
      if (!w.present[j] || (all && !w.checks[i] && !w.checks[j]) || !near(p, w, i, j)) continue;
      bool hit, will;
      T tx, ty;
      separating_axes(p, w, i, j, hit, will, tx, ty, p.length, p.width);
      if (hit) w.crashed[i] = w.crashed[j] = true;
      if (will) {
        w.impact[i] = w.impact[j] = true;
        w.ix[i] = tx / T(2), w.iy[i] = ty / T(2);
        w.ix[j] = -tx / T(2), w.iy[j] = -ty / T(2);
      }
    }
  }
}

}  // namespace highway
