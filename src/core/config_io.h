#pragma once
/// @file config_io.h
/// Loading options structs (options.h) from YAML with cv::FileStorage.
///
/// Keys absent from the file keep their defaults. An enum field (options::Names) is read as
/// one of its names. A key the options do not know, a value of
/// the wrong type or out of range is an error naming the file, the dotted key, what was
/// expected and what was found, e.g.
///   `configs/slam/x.yaml: key 'tracking.fast_threshold': expected an integer in [1, 255], found
///   300`

#include <set>
#include <string>
#include <string_view>
#include <type_traits>

#include <opencv2/core.hpp>
#include <opencv2/core/persistence.hpp>

#include "core/options.h"
#include "core/status.h"

namespace mer::options {

/// Scalar parsers: return false and fill `found` with a printable form of the node when
/// the node is not of the requested type.
bool read_scalar(const cv::FileNode& n, bool& out, std::string& found);
bool read_scalar(const cv::FileNode& n, int& out, std::string& found);
bool read_scalar(const cv::FileNode& n, std::int64_t& out, std::string& found);
bool read_scalar(const cv::FileNode& n, double& out, std::string& found);
bool read_scalar(const cv::FileNode& n, std::string& out, std::string& found);

/// Printable form of an arbitrary node (for "found ..." in messages).
std::string describe_node(const cv::FileNode& n);

/// Visitor that reads fields from a YAML mapping node; the first error wins.
class YamlReader {
 public:
  /// `file` names the source in messages; `node` is the mapping for this section.
  YamlReader(std::string file, cv::FileNode node, std::string prefix = {})
      : file_(std::move(file)), node_(node), prefix_(std::move(prefix)) {}

  template <typename T, typename C = Any>
  void field(std::string_view key, T& value, std::string_view /*doc*/, const C& c = {}) {
    known_.insert(std::string(key));
    if (!status_.is_ok()) return;
    if (!has_key(key)) return;  // absent: keep the default
    const cv::FileNode n = node_[std::string(key)];
    std::string found;
    if constexpr (std::is_enum_v<T>) {
      static_assert(std::is_same_v<C, Names<T>>, "an enum field needs options::Names<E>");
      std::string word;
      if (!read_scalar(n, word, found)) {
        fail(key, describe_expected<T>(c), found);
      } else if (!parse_name(word, c.words, value)) {
        fail(key, describe_expected<T>(c), format_value(word));
      }
    } else {
      T parsed{};
      if (!read_scalar(n, parsed, found)) {
        fail(key, describe_expected<T>(c), found);
        return;
      }
      if (!satisfies(parsed, c)) {
        fail(key, describe_expected<T>(c), format_value(parsed));
        return;
      }
      value = parsed;
    }
  }

  template <typename S>
  void section(std::string_view key, S& sub, std::string_view /*doc*/) {
    known_.insert(std::string(key));
    if (!status_.is_ok()) return;
    if (!has_key(key)) return;
    const cv::FileNode n = node_[std::string(key)];
    if (!n.isMap()) {
      fail(key, "a mapping (section)", describe_node(n));
      return;
    }
    YamlReader inner(file_, n, prefix_ + std::string(key) + ".");
    sub.visit(inner);
    inner.check_unknown_keys();
    if (!inner.status_.is_ok()) status_ = inner.status_;
  }

  /// Flags keys present in the node that no field or section consumed (typos).
  void check_unknown_keys();

  /// First error, or ok.
  const Status& status() const { return status_; }

 private:
  bool has_key(std::string_view key) const;
  void fail(std::string_view key, const std::string& expected, const std::string& found);

  std::string file_;
  cv::FileNode node_;
  std::string prefix_;
  std::set<std::string> known_;
  Status status_;
};

/// Loads `opts` from the YAML file `path` (keys absent keep their values), then validates.
template <typename S>
Status load_yaml_file(const std::string& path, S& opts);

/// Loads `opts` from YAML text (for tests and built-in profiles); `name` is used in messages.
template <typename S>
Status load_yaml_string(const std::string& name, const std::string& text, S& opts);

/// Opens a YAML file or string. Errors (missing file, malformed YAML) name the file.
Status open_yaml(const std::string& name, const std::string& file_or_text, bool is_text,
                 cv::FileStorage& fs);

namespace detail {
template <typename S>
Status load_root(const std::string& name, cv::FileStorage& fs, S& opts) {
  const cv::FileNode root = fs.root();
  if (!root.isMap() && !root.empty()) {
    return invalid_argument(name + ": expected a YAML mapping at the top level");
  }
  YamlReader reader(name, root);
  opts.visit(reader);
  reader.check_unknown_keys();
  if (!reader.status().is_ok()) return reader.status();
  Status s = validate(opts);
  if (!s.is_ok()) return Status(s.code(), name + ": " + s.message());
  return Status::ok();
}
}  // namespace detail

template <typename S>
Status load_yaml_file(const std::string& path, S& opts) {
  cv::FileStorage fs;
  Status s = open_yaml(path, path, false, fs);
  if (!s.is_ok()) return s;
  return detail::load_root(path, fs, opts);
}

template <typename S>
Status load_yaml_string(const std::string& name, const std::string& text, S& opts) {
  cv::FileStorage fs;
  Status s = open_yaml(name, text, true, fs);
  if (!s.is_ok()) return s;
  return detail::load_root(name, fs, opts);
}

}  // namespace mer::options
