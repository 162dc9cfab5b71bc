// Options layer: YAML loading, validation, error messages and the printed form.
#include "core/options.h"

#include <sstream>

#include <gtest/gtest.h>

#include "app/slam_config.h"
#include "core/config_io.h"

namespace mer {
namespace {

struct Inner {
  int count = 3;
  double ratio = 0.5;
  template <class V>
  void visit(V& v) {
    v.field("count", count, "a count", options::Range<int>{1, 10});
    v.field("ratio", ratio, "a ratio", options::Range<double>{0.0, 1.0});
  }
};

constexpr std::array<std::string_view, 2> kWords{"alpha", "beta"};

struct Outer {
  bool flag = false;
  std::string word = "alpha";
  Inner inner;
  template <class V>
  void visit(V& v) {
    v.field("flag", flag, "a flag");
    v.field("word", word, "a word", options::OneOf{kWords});
    v.section("inner", inner, "inner section");
  }
};

TEST(Options, AbsentKeysKeepDefaults) {
  Outer o;
  ASSERT_TRUE(options::load_yaml_string("t.yaml", "flag: true\n", o).is_ok());
  EXPECT_TRUE(o.flag);
  EXPECT_EQ(o.word, "alpha");
  EXPECT_EQ(o.inner.count, 3);
}

TEST(Options, LoadsNestedValues) {
  Outer o;
  const Status s =
      options::load_yaml_string("t.yaml", "word: beta\ninner:\n  count: 7\n  ratio: 0.25\n", o);
  ASSERT_TRUE(s.is_ok()) << s.message();
  EXPECT_EQ(o.word, "beta");
  EXPECT_EQ(o.inner.count, 7);
  EXPECT_DOUBLE_EQ(o.inner.ratio, 0.25);
}

TEST(Options, IntAcceptedForDouble) {
  Outer o;
  ASSERT_TRUE(options::load_yaml_string("t.yaml", "inner:\n  ratio: 1\n", o).is_ok());
  EXPECT_DOUBLE_EQ(o.inner.ratio, 1.0);
}

TEST(Options, OutOfRangeNamesFileKeyExpectedAndFound) {
  Outer o;
  const Status s = options::load_yaml_string("cfg.yaml", "inner:\n  count: 42\n", o);
  ASSERT_EQ(s.code(), StatusCode::kInvalidArgument);
  EXPECT_NE(s.message().find("cfg.yaml"), std::string::npos) << s.message();
  EXPECT_NE(s.message().find("'inner.count'"), std::string::npos) << s.message();
  EXPECT_NE(s.message().find("[1, 10]"), std::string::npos) << s.message();
  EXPECT_NE(s.message().find("42"), std::string::npos) << s.message();
  EXPECT_EQ(o.inner.count, 3) << "a rejected value must not be stored";
}

TEST(Options, WrongTypeIsRejected) {
  Outer o;
  Status s = options::load_yaml_string("c.yaml", "inner:\n  count: 2.5\n", o);
  EXPECT_EQ(s.code(), StatusCode::kInvalidArgument);
  EXPECT_NE(s.message().find("expected an integer"), std::string::npos) << s.message();
  s = options::load_yaml_string("c.yaml", "flag: maybe\n", o);
  EXPECT_NE(s.message().find("'flag'"), std::string::npos) << s.message();
  EXPECT_NE(s.message().find("maybe"), std::string::npos) << s.message();
  s = options::load_yaml_string("c.yaml", "inner: 3\n", o);
  EXPECT_NE(s.message().find("a mapping"), std::string::npos) << s.message();
}

TEST(Options, EmptyValueIsAnErrorNotADefault) {
  Outer o;
  const Status s = options::load_yaml_string("c.yaml", "inner:\n  count:\n", o);
  ASSERT_EQ(s.code(), StatusCode::kInvalidArgument);
  EXPECT_NE(s.message().find("'inner.count'"), std::string::npos) << s.message();
}

TEST(Options, UnknownKeyIsAnError) {
  Outer o;
  const Status s = options::load_yaml_string("c.yaml", "inner:\n  cuont: 2\n", o);
  ASSERT_EQ(s.code(), StatusCode::kInvalidArgument);
  EXPECT_NE(s.message().find("'inner.cuont'"), std::string::npos) << s.message();
  EXPECT_NE(s.message().find("unknown key"), std::string::npos) << s.message();
}

// A repeated key (a section pasted twice) is an error: only the first would be read.
TEST(Options, RepeatedKeyIsAnError) {
  Outer o;
  Status s = options::load_yaml_string("c.yaml", "inner:\n  count: 2\ninner:\n  count: 3\n", o);
  ASSERT_EQ(s.code(), StatusCode::kInvalidArgument);
  EXPECT_NE(s.message().find("c.yaml"), std::string::npos) << s.message();
  EXPECT_NE(s.message().find("'inner'"), std::string::npos) << s.message();
  EXPECT_NE(s.message().find("twice"), std::string::npos) << s.message();
  s = options::load_yaml_string("c.yaml", "inner:\n  count: 2\n  count: 3\n", o);
  ASSERT_EQ(s.code(), StatusCode::kInvalidArgument);
  EXPECT_NE(s.message().find("'inner.count'"), std::string::npos) << s.message();
}

TEST(Options, OneOfRejectsOtherWords) {
  Outer o;
  const Status s = options::load_yaml_string("c.yaml", "word: gamma\n", o);
  ASSERT_FALSE(s.is_ok());
  EXPECT_NE(s.message().find("one of {alpha, beta}"), std::string::npos) << s.message();
}

TEST(Options, MalformedYamlNamesFile) {
  Outer o;
  const Status s = options::load_yaml_string("bad.yaml", "inner: [1, 2\n  count: {\n", o);
  ASSERT_EQ(s.code(), StatusCode::kInvalidArgument);
  EXPECT_NE(s.message().find("bad.yaml"), std::string::npos) << s.message();
}

TEST(Options, MissingFileNamesFile) {
  Outer o;
  const Status s = options::load_yaml_file("/nonexistent/x.yaml", o);
  ASSERT_EQ(s.code(), StatusCode::kInvalidArgument);
  EXPECT_NE(s.message().find("/nonexistent/x.yaml"), std::string::npos);
}

TEST(Options, ValidatorCatchesProgrammaticValues) {
  Outer o;
  o.inner.ratio = 2.0;
  const Status s = options::validate(o);
  ASSERT_FALSE(s.is_ok());
  EXPECT_NE(s.message().find("'inner.ratio'"), std::string::npos) << s.message();
}

// The printed configuration is valid YAML that loads back to the same values.
TEST(Options, PrintedSlamConfigRoundTrips) {
  app::SlamConfig a;
  a.tracking.extractor.fast_threshold = 33;
  a.pipeline.mode = SensorMode::kRgbd;
  a.camera.synthetic.noise_sigma = 1.25;
  a.board.lock_memory = true;
  std::ostringstream os;
  options::print(a, os);
  app::SlamConfig b;
  const Status s = options::load_yaml_string("printed", os.str(), b);
  ASSERT_TRUE(s.is_ok()) << s.message() << "\n" << os.str();
  std::ostringstream os2;
  options::print(b, os2);
  EXPECT_EQ(os.str(), os2.str());
  EXPECT_EQ(b.tracking.extractor.fast_threshold, 33);
  EXPECT_EQ(b.pipeline.mode, SensorMode::kRgbd);
  EXPECT_DOUBLE_EQ(b.camera.synthetic.noise_sigma, 1.25);
  EXPECT_TRUE(b.board.lock_memory);
}

TEST(Options, DefaultSlamConfigIsValid) {
  app::SlamConfig c;
  EXPECT_TRUE(options::validate(c).is_ok());
}

}  // namespace
}  // namespace mer

namespace mer {
namespace {
TEST(Options, TrailingCommentsOnWordsAndBooleansAreIgnored) {
  Outer o;
  const Status s =
      options::load_yaml_string("c.yaml", "flag: true  # on\nword: beta # the second\n", o);
  ASSERT_TRUE(s.is_ok()) << s.message();
  EXPECT_TRUE(o.flag);
  EXPECT_EQ(o.word, "beta");
}
}  // namespace
}  // namespace mer
