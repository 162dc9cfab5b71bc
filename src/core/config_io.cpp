#include "core/config_io.h"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <limits>
#include <set>
#include <sstream>

namespace mer::options {

std::string describe_node(const cv::FileNode& n) {
  if (n.isNone()) return "nothing";
  if (n.isInt()) return std::to_string(static_cast<int>(n));
  if (n.isReal()) {
    std::ostringstream os;
    os << static_cast<double>(n);
    return os.str();
  }
  if (n.isString()) {
    // cv::FileStorage reads a key with no value as the string "..." (or an empty one).
    const std::string s = static_cast<std::string>(n);
    if (s.empty() || s == "...") return "nothing (empty value)";
    return "'" + s + "'";
  }
  if (n.isMap()) return "a mapping";
  if (n.isSeq()) return "a sequence";
  return "an unreadable value";
}

namespace {
// cv::FileStorage keeps an unquoted scalar's trailing "# comment" as part of the string;
// words and booleans never contain " #", so strip it.
std::string strip_comment(std::string s) {
  for (std::size_t i = 0; i + 1 < s.size(); ++i) {
    if ((s[i] == ' ' || s[i] == '\t') && s[i + 1] == '#') {
      s.resize(i);
      break;
    }
  }
  while (!s.empty() && (s.back() == ' ' || s.back() == '\t')) s.pop_back();
  return s;
}
}  // namespace

bool read_scalar(const cv::FileNode& n, bool& out, std::string& found) {
  if (n.isInt()) {
    const int v = static_cast<int>(n);
    if (v == 0 || v == 1) {
      out = v == 1;
      return true;
    }
  } else if (n.isString()) {
    std::string s = strip_comment(static_cast<std::string>(n));
    std::transform(s.begin(), s.end(), s.begin(),
                   [](unsigned char ch) { return static_cast<char>(std::tolower(ch)); });
    if (s == "true" || s == "yes" || s == "on") {
      out = true;
      return true;
    }
    if (s == "false" || s == "no" || s == "off") {
      out = false;
      return true;
    }
  }
  found = describe_node(n);
  return false;
}

bool read_scalar(const cv::FileNode& n, int& out, std::string& found) {
  if (n.isInt()) {
    out = static_cast<int>(n);
    return true;
  }
  found = describe_node(n);
  return false;
}

bool read_scalar(const cv::FileNode& n, std::int64_t& out, std::string& found) {
  if (n.isInt()) {
    out = static_cast<int>(n);
    return true;
  }
  // Large integers: OpenCV stores integers as 32-bit; accept integral reals.
  if (n.isReal()) {
    const double d = static_cast<double>(n);
    if (std::floor(d) == d && std::abs(d) < 9.0e15) {
      out = static_cast<std::int64_t>(d);
      return true;
    }
  }
  found = describe_node(n);
  return false;
}

bool read_scalar(const cv::FileNode& n, double& out, std::string& found) {
  if (n.isReal() || n.isInt()) {
    out = n.isInt() ? static_cast<double>(static_cast<int>(n)) : static_cast<double>(n);
    if (std::isfinite(out)) return true;
  }
  found = describe_node(n);
  return false;
}

bool read_scalar(const cv::FileNode& n, std::string& out, std::string& found) {
  if (n.isString()) {
    out = strip_comment(static_cast<std::string>(n));
    return true;
  }
  found = describe_node(n);
  return false;
}

void YamlReader::fail(std::string_view key, const std::string& expected, const std::string& found) {
  if (!status_.is_ok()) return;
  status_ = invalid_argument(file_ + ": key '" + prefix_ + std::string(key) + "': expected " +
                             expected + ", found " + found);
}

bool YamlReader::has_key(std::string_view key) const {
  if (!node_.isMap()) return false;
  for (const cv::FileNode& child : node_) {
    if (child.name() == key) return true;
  }
  return false;
}

void YamlReader::check_unknown_keys() {
  if (!status_.is_ok() || !node_.isMap()) return;
  std::set<std::string> seen;
  for (const cv::FileNode& child : node_) {
    const std::string name = child.name();
    // cv::FileStorage keeps both entries of a repeated key but lookups find the first only:
    // the second (often a whole section pasted twice) would be ignored without a word.
    if (!seen.insert(name).second) {
      status_ = invalid_argument(file_ + ": key '" + prefix_ + name +
                                 "': given twice at this level (merge the two)");
      return;
    }
    if (known_.count(name) == 0) {
      std::string known_list;
      for (const auto& k : known_) known_list += (known_list.empty() ? "" : ", ") + k;
      status_ = invalid_argument(file_ + ": key '" + prefix_ + name +
                                 "': unknown key (known here: " + known_list + ")");
      return;
    }
  }
}

Status open_yaml(const std::string& name, const std::string& file_or_text, bool is_text,
                 cv::FileStorage& fs) {
  std::string text = file_or_text;
  if (!is_text) {
    std::error_code ec;
    if (!std::filesystem::is_regular_file(file_or_text, ec)) {
      return invalid_argument(name + ": config file not found or not a regular file");
    }
    std::ifstream in(file_or_text);
    if (!in) return invalid_argument(name + ": cannot read config file");
    std::ostringstream ss;
    ss << in.rdbuf();
    text = ss.str();
  }
  // cv::FileStorage wants the YAML directive; accept plain YAML files without it.
  if (text.rfind("%YAML", 0) != 0) text = "%YAML:1.0\n---\n" + text;
  try {
    if (!fs.open(text,
                 cv::FileStorage::READ | cv::FileStorage::MEMORY | cv::FileStorage::FORMAT_YAML)) {
      return invalid_argument(name + ": not a readable YAML document");
    }
  } catch (const cv::Exception& e) {
    std::string msg = e.msg;
    // OpenCV messages end with a newline and carry a long prefix; keep the gist.
    while (!msg.empty() && (msg.back() == '\n' || msg.back() == ' ')) msg.pop_back();
    return invalid_argument(name + ": malformed YAML: " + msg);
  }
  return Status::ok();
}

}  // namespace mer::options
