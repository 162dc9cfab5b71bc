#pragma once
/// @file options.h
/// The typed options layer. Every module has one options struct with defaults in place and
/// a `visit(V&)` member that names each field once, with its key, a doc line and its
/// constraint. The same description drives loading from YAML (config_io.h), validation,
/// printing (`mer_slam --print-config`) and docs, so a field cannot be loaded but not
/// validated or printed. The doc line is the field's one documentation: the member itself
/// carries no comment that could drift from it.
///
/// @code
/// struct TrackingOptions {
///   int fast_threshold = 20;
///   template <class V> void visit(V& v) {
///     v.field("fast_threshold", fast_threshold, "FAST intensity threshold", Range<int>{1, 255});
///   }
/// };
/// @endcode
///
/// A field may also be an enum, written in YAML as one of its names: the constraint
/// `Names<E>{kWords}` lists them, `kWords[i]` naming `static_cast<E>(i)`. The word is parsed
/// once, on loading; the code then compares enumerators.

#include <cstddef>
#include <cstdint>
#include <span>
#include <sstream>
#include <string>
#include <string_view>
#include <type_traits>

#include "core/status.h"

namespace mer::options {

/// Any value of the type is accepted.
struct Any {};

/// Inclusive numeric range.
template <typename T>
struct Range {
  T lo;  ///< smallest accepted value
  T hi;  ///< largest accepted value
};

/// A string that must be one of a fixed set of words (an enum in YAML).
struct OneOf {
  std::span<const std::string_view> words;  ///< accepted values
};

/// An enum field written as one of a fixed set of words: `words[i]` is the name of
/// `static_cast<E>(i)` (the enumerators are 0, 1, ... in the order of the list).
template <typename E>
struct Names {
  static_assert(std::is_enum_v<E>, "options::Names is the constraint of an enum field");
  std::span<const std::string_view> words;  ///< name of each enumerator, by value
};

/// Name of enumerator `value` in `words` (empty when the value has none).
template <typename E>
std::string_view name_of(E value, std::span<const std::string_view> words) {
  using U = std::underlying_type_t<E>;
  const auto i = static_cast<U>(value);
  if constexpr (std::is_signed_v<U>) {
    if (i < 0) return {};
  }
  if (static_cast<std::size_t>(i) >= words.size()) return {};
  return words[static_cast<std::size_t>(i)];
}

/// Sets `out` to the enumerator named `word` in `words`; false (out unchanged) when none is.
template <typename E>
bool parse_name(std::string_view word, std::span<const std::string_view> words, E& out) {
  for (std::size_t i = 0; i < words.size(); ++i) {
    if (words[i] == word) {
      out = static_cast<E>(i);
      return true;
    }
  }
  return false;
}

/// Human description of what a field accepts, for error messages and printing.
template <typename T, typename C>
std::string describe_expected(const C& c) {
  std::ostringstream os;
  if constexpr (std::is_same_v<T, bool>) {
    os << "a boolean (true/false)";
  } else if constexpr (std::is_integral_v<T>) {
    os << "an integer";
  } else if constexpr (std::is_floating_point_v<T>) {
    os << "a number";
  } else {
    os << "a string";
  }
  if constexpr (std::is_same_v<C, Range<T>>) {
    os << " in [" << c.lo << ", " << c.hi << "]";
  } else if constexpr (std::is_same_v<C, OneOf> || std::is_same_v<C, Names<T>>) {
    os << ", one of {";
    for (std::size_t i = 0; i < c.words.size(); ++i) os << (i ? ", " : "") << c.words[i];
    os << "}";
  }
  return os.str();
}

/// True when `value` satisfies constraint `c`.
template <typename T, typename C>
bool satisfies(const T& value, const C& c) {
  if constexpr (std::is_same_v<C, Range<T>>) {
    return value >= c.lo && value <= c.hi;
  } else if constexpr (std::is_same_v<C, OneOf>) {
    for (auto w : c.words) {
      if (w == value) return true;
    }
    return false;
  } else if constexpr (std::is_same_v<C, Names<T>>) {
    return !name_of(value, c.words).empty();
  } else {
    (void)value;
    (void)c;
    return true;
  }
}

/// Formats a value the way YAML (and our reader) expects it.
template <typename T>
std::string format_value(const T& value) {
  std::ostringstream os;
  if constexpr (std::is_same_v<T, bool>) {
    os << (value ? "true" : "false");
  } else if constexpr (std::is_same_v<T, std::string>) {
    os << '"' << value << '"';
  } else if constexpr (std::is_floating_point_v<T>) {
    os.precision(10);
    os << value;
    // Keep a decimal point so the value reads back as a real, not an int.
    const std::string s = os.str();
    if (s.find_first_of(".eEn") == std::string::npos) os << ".0";
  } else if constexpr (std::is_enum_v<T>) {
    os << static_cast<long long>(value);  // without its names: the number
  } else {
    os << value;
  }
  return os.str();
}

/// Formats a field's value given its constraint: an enum by its name, in double quotes.
template <typename T, typename C>
std::string format_value(const T& value, const C& c) {
  if constexpr (std::is_same_v<C, Names<T>>) {
    const std::string_view name = name_of(value, c.words);
    if (!name.empty()) return format_value(std::string(name));
  }
  (void)c;
  return format_value(value);
}

/// Sets enum field `out` from `word`, a value given outside YAML (a command-line flag); an
/// unknown word is an error naming `key` and the accepted words, as the YAML loader's is.
template <typename E>
Status set_by_name(std::string_view key, std::string_view word, const Names<E>& c, E& out) {
  if (parse_name(word, c.words, out)) return Status::ok();
  return invalid_argument("key '" + std::string(key) + "': expected " + describe_expected<E>(c) +
                          ", found " + format_value(std::string(word)));
}

/// Visitor that checks every field against its constraint; the first failure wins.
/// `prefix` is the dotted path of the section ("tracking.").
class Validator {
 public:
  explicit Validator(std::string prefix = {}) : prefix_(std::move(prefix)) {}

  template <typename T, typename C = Any>
  void field(std::string_view key, T& value, std::string_view /*doc*/, const C& c = {}) {
    if (!status_.is_ok() || satisfies(value, c)) return;
    status_ = invalid_argument("key '" + prefix_ + std::string(key) + "': expected " +
                               describe_expected<T>(c) + ", found " + format_value(value, c));
  }

  template <typename S>
  void section(std::string_view key, S& sub, std::string_view /*doc*/) {
    if (!status_.is_ok()) return;
    Validator inner(prefix_ + std::string(key) + ".");
    sub.visit(inner);
    if (!inner.status_.is_ok()) status_ = inner.status_;
  }

  /// First violation found, or ok.
  const Status& status() const { return status_; }

 private:
  std::string prefix_;
  Status status_;
};

/// Visitor that prints the options as commented YAML (loadable again with config_io).
class Printer {
 public:
  explicit Printer(std::ostream& os, int indent = 0) : os_(os), indent_(indent) {}

  template <typename T, typename C = Any>
  void field(std::string_view key, T& value, std::string_view doc, const C& c = {}) {
    pad();
    os_ << "# " << doc << " [" << describe_expected<T>(c) << "]\n";
    pad();
    os_ << key << ": " << format_value(value, c) << "\n";
  }

  template <typename S>
  void section(std::string_view key, S& sub, std::string_view doc) {
    pad();
    os_ << "# " << doc << "\n";
    pad();
    os_ << key << ":\n";
    Printer inner(os_, indent_ + 2);
    sub.visit(inner);
  }

 private:
  void pad() { os_ << std::string(static_cast<std::size_t>(indent_), ' '); }
  std::ostream& os_;
  int indent_;
};

/// Validates a whole options struct (or the top-level config).
template <typename S>
Status validate(S& opts) {
  Validator v;
  opts.visit(v);
  return v.status();
}

/// Prints a whole options struct as commented YAML.
template <typename S>
void print(S& opts, std::ostream& os) {
  Printer p(os);
  opts.visit(p);
}

}  // namespace mer::options
