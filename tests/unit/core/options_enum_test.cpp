// Enum option fields (options::Names): loaded from one of their names, printed as the name in
// double quotes exactly like a OneOf string, validated, and rejected with the accepted words.
#include <array>
#include <cstdint>
#include <sstream>
#include <string>
#include <string_view>

#include <gtest/gtest.h>

#include "core/config_io.h"
#include "core/options.h"

namespace mer {
namespace {

enum class Colour : std::uint8_t { kRed, kGreen, kBlue };
constexpr std::array<std::string_view, 3> kColourNames{"red", "green", "blue"};

// The same choice as an enum and as a string, so their printed forms can be compared.
struct Paint {
  Colour colour = Colour::kGreen;
  std::string word = "green";
  template <class V>
  void visit(V& v) {
    v.field("colour", colour, "a colour", options::Names<Colour>{kColourNames});
    v.field("word", word, "a colour", options::OneOf{kColourNames});
  }
};

TEST(OptionsEnum, NamesMapToEnumerators) {
  EXPECT_EQ(options::name_of(Colour::kRed, kColourNames), "red");
  EXPECT_EQ(options::name_of(Colour::kBlue, kColourNames), "blue");
  EXPECT_EQ(options::name_of(static_cast<Colour>(3), kColourNames), "");
  Colour c = Colour::kRed;
  ASSERT_TRUE(options::parse_name("blue", kColourNames, c));
  EXPECT_EQ(c, Colour::kBlue);
  EXPECT_FALSE(options::parse_name("Blue", kColourNames, c));
  EXPECT_EQ(c, Colour::kBlue) << "a refused word must not change the value";
}

TEST(OptionsEnum, LoadsAName) {
  Paint p;
  const Status s = options::load_yaml_string("t.yaml", "colour: blue\n", p);
  ASSERT_TRUE(s.is_ok()) << s.message();
  EXPECT_EQ(p.colour, Colour::kBlue);
  Paint q;
  ASSERT_TRUE(options::load_yaml_string("t.yaml", "colour: \"red\"  # quoted\n", q).is_ok());
  EXPECT_EQ(q.colour, Colour::kRed);
  Paint r;
  ASSERT_TRUE(options::load_yaml_string("t.yaml", "colour: red # comment\n", r).is_ok());
  EXPECT_EQ(r.colour, Colour::kRed);
  Paint d;
  ASSERT_TRUE(options::load_yaml_string("t.yaml", "word: red\n", d).is_ok());
  EXPECT_EQ(d.colour, Colour::kGreen) << "an absent key keeps its default";
}

// The printed form is the one a OneOf string field of the same value has.
TEST(OptionsEnum, PrintsLikeAOneOfString) {
  Paint p;
  p.colour = Colour::kBlue;
  p.word = "blue";
  std::ostringstream os;
  options::print(p, os);
  EXPECT_EQ(os.str(),
            "# a colour [a string, one of {red, green, blue}]\n"
            "colour: \"blue\"\n"
            "# a colour [a string, one of {red, green, blue}]\n"
            "word: \"blue\"\n");
}

TEST(OptionsEnum, PrintedFormRoundTrips) {
  for (Colour c : {Colour::kRed, Colour::kGreen, Colour::kBlue}) {
    Paint a;
    a.colour = c;
    std::ostringstream os;
    options::print(a, os);
    Paint b;
    b.colour = c == Colour::kRed ? Colour::kBlue : Colour::kRed;
    const Status s = options::load_yaml_string("printed", os.str(), b);
    ASSERT_TRUE(s.is_ok()) << s.message() << "\n" << os.str();
    EXPECT_EQ(b.colour, c);
    std::ostringstream os2;
    options::print(b, os2);
    EXPECT_EQ(os.str(), os2.str());
  }
}

// An unknown word names the file and key and lists the accepted words, as OneOf does.
TEST(OptionsEnum, UnknownWordNamesKeyAndAcceptedWords) {
  Paint p;
  const Status s = options::load_yaml_string("c.yaml", "colour: purple\n", p);
  ASSERT_EQ(s.code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(s.message(),
            "c.yaml: key 'colour': expected a string, one of {red, green, blue}, found \"purple\"");
  EXPECT_EQ(p.colour, Colour::kGreen) << "a rejected word must not be stored";
  const Status w = options::load_yaml_string("c.yaml", "word: purple\n", p);
  EXPECT_EQ(w.message(),
            "c.yaml: key 'word': expected a string, one of {red, green, blue}, found \"purple\"");
}

TEST(OptionsEnum, NonStringIsRejected) {
  Paint p;
  const Status s = options::load_yaml_string("c.yaml", "colour: 2\n", p);
  ASSERT_EQ(s.code(), StatusCode::kInvalidArgument);
  EXPECT_EQ(s.message(),
            "c.yaml: key 'colour': expected a string, one of {red, green, blue}, found 2");
  EXPECT_EQ(p.colour, Colour::kGreen);
}

TEST(OptionsEnum, ValidatorRejectsAValueWithoutAName) {
  Paint p;
  EXPECT_TRUE(options::validate(p).is_ok());
  p.colour = static_cast<Colour>(7);
  const Status s = options::validate(p);
  ASSERT_FALSE(s.is_ok());
  EXPECT_EQ(s.message(), "key 'colour': expected a string, one of {red, green, blue}, found 7");
}

}  // namespace
}  // namespace mer
