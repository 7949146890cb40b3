// Optional phase timers and pair counters of the CPU kernels, compiled out by default.
//
// Build with COBGS_PROFILE=1 in the environment (cobgs/render/_build.py then adds -DCOBGS_PROFILE,
// a separate cached build) to get, at process exit on stderr, the thread CPU time of every
// phase summed over threads and calls, the number of calls of each op, and the
// (Gaussian, pixel) pair counts of the blending kernels. Thread CPU time rather than wall
// time: on a machine shared with other jobs, wall time mostly measures waiting for a core.
#pragma once

#ifdef COBGS_PROFILE
#include <time.h>

#include <atomic>
#include <cstdint>
#include <cstdio>

namespace cobgs {
namespace prof {

enum Timer {
  kProject, kProjectBwd, kBinPrepare, kBinSort, kBinLists, kFwdPrepare, kFwdTiles, kFwdLabels,
  kBwdPrepare, kBwdGroup, kBwdTiles, kBwdReduce, kBwdBackground, kShFwd, kShBwd, kNumTimers
};
enum Count {
  kCallsProject, kCallsProjectBwd, kCallsBin, kCallsFwd, kCallsBwd, kCallsSh, kCallsShBwd,
  kFwdEntries,       // tile-list entries visited by the forward
  kFwdBlocks,        // 8-pixel blocks evaluated (power computed)
  kFwdBlocksExp,     // ... of which reached exp (some lane within the power bound)
  kFwdBlended,       // (Gaussian, pixel) pairs blended
  kBwdBlocks, kBwdBlocksExp, kBwdBlended,
  kNumCounts
};

struct Stats {
  std::atomic<int64_t> ns[kNumTimers];
  std::atomic<int64_t> count[kNumCounts];
  Stats() {
    for (auto& v : ns) v = 0;
    for (auto& v : count) v = 0;
  }
  ~Stats() {
    static const char* tn[kNumTimers] = {
        "project", "project_bwd", "bin_tiles: prepare", "bin_tiles: depth sort", "bin_tiles: tile lists",
        "blend: prepare", "blend: tiles", "blend: label reduction", "blend_bwd: prepare",
        "blend_bwd: group entries", "blend_bwd: tiles", "blend_bwd: reduction",
        "blend_bwd: background", "sh_colors", "sh_colors_bwd"};
    static const char* cn[kNumCounts] = {
        "calls project", "calls project_bwd", "calls bin_tiles", "calls blend",
        "calls blend_bwd", "calls sh_colors", "calls sh_colors_bwd", "blend: entries",
        "blend: blocks evaluated", "blend: blocks reaching exp", "blend: pairs blended",
        "blend_bwd: blocks evaluated", "blend_bwd: blocks reaching exp",
        "blend_bwd: pairs blended"};
    std::fprintf(stderr, "cobgs profile (thread CPU ms, summed over threads and calls):\n");
    for (int i = 0; i < kNumTimers; ++i)
      std::fprintf(stderr, "  %-28s %10.2f\n", tn[i], double(ns[i].load()) * 1e-6);
    for (int i = 0; i < kNumCounts; ++i)
      std::fprintf(stderr, "  %-28s %12lld\n", cn[i], static_cast<long long>(count[i].load()));
  }
};

inline Stats& stats() {
  static Stats s;
  return s;
}

inline int64_t thread_ns() {
  timespec ts;
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return int64_t(ts.tv_sec) * 1000000000 + ts.tv_nsec;
}

struct Scope {
  Timer id;
  int64_t t0;
  explicit Scope(Timer i) : id(i), t0(thread_ns()) {}
  ~Scope() { stats().ns[id] += thread_ns() - t0; }
};

}  // namespace prof
}  // namespace cobgs

#define COBGS_PROF_CAT2(a, b) a##b
#define COBGS_PROF_CAT(a, b) COBGS_PROF_CAT2(a, b)
#define COBGS_PROF_SCOPE(id) \
  ::cobgs::prof::Scope COBGS_PROF_CAT(cobgs_prof_, __LINE__)(::cobgs::prof::id)
#define COBGS_PROF_COUNT(id, v) (::cobgs::prof::stats().count[::cobgs::prof::id] += (v))
#define COBGS_PROF_LOCAL(name) int64_t name = 0
#define COBGS_PROF_ADD(name, v) (name += (v))
#else
#define COBGS_PROF_SCOPE(id) ((void)0)
#define COBGS_PROF_COUNT(id, v) ((void)0)
#define COBGS_PROF_LOCAL(name) ((void)0)
#define COBGS_PROF_ADD(name, v) ((void)0)
#endif
