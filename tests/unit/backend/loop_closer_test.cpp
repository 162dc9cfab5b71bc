// Loop-closure retrieval keys: each table reads its own bits of the descriptor, so a bit no
// table uses changes no key and a bit one table uses changes that table's key only.
#include "backend/loop_closer.h"

#include <gtest/gtest.h>

#include "support/doc_check.h"

namespace mer::backend {
namespace {

TEST(LoopCloserKeys, EachTableReadsItsOwnBits) {
  const features::Descriptor d{0x0123456789abcdefULL, 0xfedcba9876543210ULL, 0x0f0f0f0f0f0f0f0fULL,
                               0x5555aaaa5555aaaaULL};
  const auto k = descriptor_keys(d);
  EXPECT_EQ(descriptor_keys(d), k);
  // Table t reads bits t, t + 4, ..., t + 60 of word t: bit 1 of word 0 is nobody's.
  features::Descriptor unused = d;
  unused[0] ^= 1ULL << 1U;
  EXPECT_EQ(descriptor_keys(unused), k);
  for (std::size_t t = 0; t < k.size(); ++t) {
    features::Descriptor flipped = d;
    flipped[t] ^= 1ULL << t;  // table t's first bit
    const auto kf = descriptor_keys(flipped);
    for (std::size_t u = 0; u < k.size(); ++u) {
      if (u == t) {
        EXPECT_NE(kf[u], k[u]) << "table " << t;
      } else {
        EXPECT_EQ(kf[u], k[u]) << "table " << u << " changed by table " << t << "'s bit";
      }
    }
  }
}

TEST(LoopOptions, EveryFieldHasADocLine) {
  testing::DocCheck v;
  LoopOptions o;
  o.visit(v);
  EXPECT_EQ(v.fields, 18);
}

}  // namespace
}  // namespace mer::backend
