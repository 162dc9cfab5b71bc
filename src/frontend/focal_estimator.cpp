#include "frontend/focal_estimator.h"

#include <cmath>

#include "core/median.h"
#include "platform/log_ring.h"

namespace mer::frontend {

FocalEstimator::FocalEstimator(const FocalOptions& opts, double initial, bool estimated)
    : opts_(opts) {
  report_.estimated = estimated;
  report_.initial = initial;
  report_.value = initial;
  report_.fixed = !estimated;
}

void FocalEstimator::reserve() {
  const auto n = static_cast<std::size_t>(opts_.max_frames) + 1024;
  estimates_.reserve(n);
  scratch_.reserve(n);
}

double FocalEstimator::median() {
  scratch_.assign(estimates_.begin(), estimates_.end());
  const double med = upper_median(scratch_);
  report_.value = med;
  report_.estimates = static_cast<int>(estimates_.size());
  return med;
}

double FocalEstimator::add_two_view(double f) {
  estimates_.push_back(f);
  return median();
}

bool FocalEstimator::add_tracked(double f, std::uint64_t seq, std::uint64_t frames_since_init) {
  if (!(f > 0.0) || !std::isfinite(f)) return false;
  if (estimates_.size() < estimates_.capacity()) estimates_.push_back(f);
  const double med = median();
  stable_count_ = std::abs(f - med) <= opts_.stable_tolerance * med ? stable_count_ + 1 : 0;
  if (stable_count_ >= opts_.stable_frames ||
      frames_since_init >= static_cast<std::uint64_t>(opts_.max_frames)) {
    report_.fixed = true;
    report_.fixed_at_seq = static_cast<std::int64_t>(seq);
    MER_LOG_INFO("focal length fixed at %.2f px (frame %llu, %d estimates)", med,
                 static_cast<unsigned long long>(seq), report_.estimates);
  }
  return true;
}

void FocalEstimator::fix_at_init(std::uint64_t seq) {
  if (!report_.estimated || report_.fixed || opts_.refine_after_init) return;
  report_.fixed = true;
  report_.fixed_at_seq = static_cast<std::int64_t>(seq);
  MER_LOG_INFO("focal length fixed at %.2f px at initialization (%d two-view estimates)",
               report_.value, report_.estimates);
}

}  // namespace mer::frontend
