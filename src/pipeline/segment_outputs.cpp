#include "pipeline/segment_outputs.h"

#include <algorithm>
#include <array>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <sstream>

#include "core/pose.h"
#include "core/timestamp.h"
#include "geometry/sim3.h"
#include "pipeline/output_stage.h"

namespace mer::pipeline {
namespace {

/// One TUM line of a segment file, as the output stage wrote it.
struct PoseLine {
  std::int64_t t_ns = 0;
  SE3d T_w_c = SE3d::Identity();
};

Status read_lines(const std::filesystem::path& path, std::vector<PoseLine>& out) {
  std::ifstream in(path);
  if (!in) return Status::ok();  // a segment without keyframes has no keyframe file
  std::string line;
  int n = 0;
  while (std::getline(in, line)) {
    ++n;
    if (line.empty() || line[0] == '#') continue;
    std::istringstream ss(line);
    std::string stamp;
    PoseLine p;
    double v[7];
    if (!(ss >> stamp >> v[0] >> v[1] >> v[2] >> v[3] >> v[4] >> v[5] >> v[6]) ||
        !parse_seconds_ns(stamp, p.t_ns)) {
      return input_error("'" + path.string() + "' line " + std::to_string(n) +
                         ": not a TUM pose line");
    }
    p.T_w_c.linear() = Eigen::Quaterniond(v[6], v[3], v[4], v[5]).normalized().toRotationMatrix();
    p.T_w_c.translation() = Eigen::Vector3d(v[0], v[1], v[2]);
    out.push_back(p);
  }
  return Status::ok();
}

Status write_lines(const std::filesystem::path& path, const std::vector<PoseLine>& lines) {
  const std::filesystem::path tmp = path.string() + ".tmp";
  std::FILE* f = std::fopen(tmp.c_str(), "w");
  if (f == nullptr) {
    return runtime_error("cannot write '" + tmp.string() + "': " + std::strerror(errno));
  }
  bool ok = true;
  std::array<char, 256> buf{};
  for (const PoseLine& p : lines) {
    const int n = format_tum_line(buf.data(), buf.size(), p.t_ns, p.T_w_c);
    ok = ok && n > 0 &&
         std::fwrite(buf.data(), 1, static_cast<std::size_t>(n), f) == static_cast<std::size_t>(n);
  }
  if (std::fclose(f) != 0 || !ok) return runtime_error("error writing '" + tmp.string() + "'");
  std::error_code ec;
  std::filesystem::rename(tmp, path, ec);
  if (ec) return runtime_error("cannot rename '" + tmp.string() + "': " + ec.message());
  return Status::ok();
}

/// How far `S` takes the keyframes `live` (a segment's, as tracked) from their `final` poses
/// (same order): mean squared position error and mean rotation error, rad.
struct FitError {
  double position2 = 0.0;
  double rotation = 0.0;
};
FitError fit_error(const geometry::Sim3d& S, std::span<const SE3d> live,
                   std::span<const SE3d> final) {
  FitError e;
  for (std::size_t i = 0; i < live.size(); ++i) {
    const SE3d T = geometry::apply_to_pose(S, live[i]);
    e.position2 += (T.translation() - final[i].translation()).squaredNorm();
    e.rotation += Eigen::AngleAxisd(T.linear().transpose() * final[i].linear()).angle();
  }
  const auto n = static_cast<double>(std::max<std::size_t>(live.size(), 1));
  e.position2 /= n;
  e.rotation /= n;
  return e;
}

}  // namespace

std::string segment_file_name(std::uint16_t segment, bool keyframes) {
  const char* kind = keyframes ? "keyframes" : "trajectory";
  if (segment == 0) return std::string(kind) + ".txt";
  return std::string(kind) + "_segment_" + std::to_string(segment) + ".txt";
}

std::vector<double> segment_scales_into(std::span<const SegmentMergeRecord> merges,
                                        std::uint16_t main, std::size_t segments) {
  std::vector<double> scales(segments, 0.0);
  for (std::size_t g = 0; g < segments; ++g) {
    double scale = 1.0;
    auto at = static_cast<std::uint16_t>(g);
    for (const SegmentMergeRecord& m : merges) {
      if (m.from != at) continue;
      scale *= m.sim_into_from.s;
      at = m.into;
    }
    if (at == main) scales[g] = scale;
  }
  return scales;
}

Status join_segment_files(const std::string& dir, std::span<const SegmentMergeRecord> merges,
                          std::vector<SegmentOutput>& segments, std::uint16_t& main,
                          const FinalKeyframesOf& final_keyframes) {
  main = 0;
  for (SegmentOutput& g : segments) g.trajectory = segment_file_name(g.id, false);
  if (segments.empty()) return Status::ok();
  // Frames of each segment after merging, and where each merged segment ended up.
  std::map<std::uint16_t, std::uint64_t> frames;
  bool any_discarded = false;
  for (const SegmentOutput& g : segments) {
    frames[g.id] = g.discarded ? 0 : g.frames;
    any_discarded = any_discarded || g.discarded;
  }
  std::map<std::uint16_t, int> merged_into;
  std::map<std::uint16_t, std::uint64_t> merged_at;
  auto discarded = [&](std::uint16_t id) {
    return std::any_of(segments.begin(), segments.end(),
                       [id](const SegmentOutput& g) { return g.id == id && g.discarded; });
  };
  for (const SegmentMergeRecord& m : merges) {
    if (discarded(m.from) || discarded(m.into)) continue;  // (the map refuses such merges)
    frames[m.into] += frames[m.from];
    frames[m.from] = 0;
    merged_at.emplace(m.from, m.seq);
    for (auto& [seg, into] : merged_into) {  // what merged into `from` before now follows it
      if (into == m.from) into = m.into;
    }
    merged_into[m.from] = m.into;
  }
  // The main segment: the most frames after merging (the lowest id on a tie).
  std::uint64_t best = 0;
  for (const auto& [id, n] : frames) {
    if (!merged_into.contains(id) && n > best) {
      best = n;
      main = id;
    }
  }
  if (dir.empty() || (merges.empty() && main == 0 && !any_discarded)) {
    for (SegmentOutput& g : segments) {
      if (g.discarded) g.trajectory.clear();
    }
    return Status::ok();  // as written
  }

  const std::filesystem::path d(dir);
  // Frames (and keyframes) of each segment, in its own frame, as the run wrote them.
  std::map<std::uint16_t, std::vector<PoseLine>> traj;
  std::map<std::uint16_t, std::vector<PoseLine>> kfs;
  for (const SegmentOutput& g : segments) {
    if (Status s = read_lines(d / segment_file_name(g.id, false), traj[g.id]); !s.is_ok()) return s;
    if (Status s = read_lines(d / segment_file_name(g.id, true), kfs[g.id]); !s.is_ok()) return s;
  }
  // A segment that ended in the main one moves there by a similarity fitted to its
  // keyframes' final poses when that is no worse, on their positions and their orientations,
  // than the merges' similarities composed (it then moves straight into the main segment).
  std::map<std::uint16_t, geometry::Sim3d> fitted;
  std::map<std::uint16_t, int> fit_keyframes;
  if (final_keyframes) {
    const std::vector<FinalKeyframePose> finals = final_keyframes(main);
    std::vector<SE3d> live;
    std::vector<SE3d> final;
    for (const auto& [id, into] : merged_into) {
      if (into != main || discarded(id)) continue;
      live.clear();
      final.clear();
      for (const PoseLine& k : kfs[id]) {
        const auto it =
            std::lower_bound(finals.begin(), finals.end(), k.t_ns,
                             [](const FinalKeyframePose& f, std::int64_t t) { return f.t_ns < t; });
        if (it == finals.end() || it->t_ns != k.t_ns) continue;
        live.push_back(k.T_w_c);
        final.push_back(it->T_w_c);
      }
      if (live.size() < kMinFitKeyframes) continue;
      geometry::Sim3d chain;  // the merges' similarities from `id` to the main segment
      std::uint16_t at = id;
      for (const SegmentMergeRecord& m : merges) {
        if (m.from != at || discarded(m.into)) continue;
        chain = m.sim_into_from * chain;
        at = m.into;
      }
      const geometry::Sim3d fit = geometry::fit_similarity_to_poses(live, final);
      const FitError e_fit = fit_error(fit, live, final);
      const FitError e_chain = fit_error(chain, live, final);
      if (e_fit.position2 <= e_chain.position2 && e_fit.rotation <= e_chain.rotation) {
        fitted[id] = fit;
        fit_keyframes[id] = static_cast<int>(live.size());
      }
    }
  }
  auto join = [](std::vector<PoseLine>& from, std::vector<PoseLine>& into,
                 const geometry::Sim3d& S) {
    for (PoseLine& p : from) {
      p.T_w_c = geometry::apply_to_pose(S, p.T_w_c);
      into.push_back(p);
    }
    from.clear();
    std::stable_sort(into.begin(), into.end(),
                     [](const PoseLine& a, const PoseLine& b) { return a.t_ns < b.t_ns; });
  };
  for (const auto& [id, S] : fitted) {
    join(traj[id], traj[main], S);
    join(kfs[id], kfs[main], S);
  }
  for (const SegmentMergeRecord& m : merges) {
    if (discarded(m.from) || discarded(m.into)) continue;
    join(traj[m.from], traj[m.into], m.sim_into_from);
    join(kfs[m.from], kfs[m.into], m.sim_into_from);
  }
  auto name = [&](std::uint16_t id, bool keyframes) {
    if (id == main) return segment_file_name(0, keyframes);
    if (id == 0) return std::string(keyframes ? "keyframes" : "trajectory") + "_segment_0.txt";
    return segment_file_name(id, keyframes);
  };
  for (SegmentOutput& g : segments) {
    if (g.discarded) {
      g.trajectory.clear();
    } else if (const auto it = merged_into.find(g.id); it != merged_into.end()) {
      g.merged_into = it->second;
      g.merged_at_seq = merged_at[g.id];
      if (const auto f = fit_keyframes.find(g.id); f != fit_keyframes.end()) {
        g.fit_keyframes = f->second;
      }
      g.trajectory = name(static_cast<std::uint16_t>(it->second), false);
    } else {
      g.trajectory = name(g.id, false);
    }
  }
  // Write every surviving segment under its new name, then remove what no segment owns.
  std::vector<std::string> written;
  bool main_kept = false;
  for (const SegmentOutput& g : segments) {
    if (merged_into.contains(g.id) || g.discarded) continue;
    main_kept = main_kept || g.id == main;
    for (const bool k : {false, true}) {
      const std::string n = name(g.id, k);
      if (Status s = write_lines(d / n, k ? kfs[g.id] : traj[g.id]); !s.is_ok()) return s;
      written.push_back(n);
    }
  }
  if (!main_kept) {  // no segment kept: trajectory.txt and keyframes.txt stay, empty
    for (const bool k : {false, true}) {
      const std::string n = segment_file_name(0, k);
      if (Status s = write_lines(d / n, {}); !s.is_ok()) return s;
      written.push_back(n);
    }
  }
  for (const SegmentOutput& g : segments) {
    for (const bool k : {false, true}) {
      const std::string n = segment_file_name(g.id, k);
      if (std::find(written.begin(), written.end(), n) == written.end()) {
        std::error_code ec;
        std::filesystem::remove(d / n, ec);
      }
    }
  }
  return Status::ok();
}

}  // namespace mer::pipeline
