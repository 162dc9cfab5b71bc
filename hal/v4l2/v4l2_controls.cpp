#include "hal/v4l2/v4l2_controls.h"

#include <fcntl.h>
#include <linux/videodev2.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>

#include "hal/v4l2/v4l2_util.h"

namespace mer::hal {
namespace {

constexpr std::size_t kMaxControls = 1024;  // bound on the enumeration loop

/// Closes a file descriptor on scope exit.
class FdGuard {
 public:
  explicit FdGuard(int fd) : fd_(fd) {}
  ~FdGuard() {
    if (fd_ >= 0) ::close(fd_);
  }
  FdGuard(const FdGuard&) = delete;
  FdGuard& operator=(const FdGuard&) = delete;
  int get() const { return fd_; }

 private:
  int fd_;
};

Result<int> open_node(const std::string& device) {
  const int fd = ::open(device.c_str(), O_RDWR | O_NONBLOCK | O_CLOEXEC);
  if (fd < 0) return input_error("v4l2:" + device + ": cannot open: " + errno_text(errno));
  return fd;
}

std::string lower(std::string_view s) {
  std::string out(s);
  std::transform(out.begin(), out.end(), out.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  return out;
}

}  // namespace

Result<std::vector<V4l2Control>> list_v4l2_controls(const std::string& device) {
  auto fd_or = open_node(device);
  if (!fd_or.is_ok()) return fd_or.status();
  FdGuard fd(fd_or.value());
  std::vector<V4l2Control> out;
  v4l2_query_ext_ctrl q{};
  q.id = V4L2_CTRL_FLAG_NEXT_CTRL | V4L2_CTRL_FLAG_NEXT_COMPOUND;
  while (out.size() < kMaxControls) {
    if (xioctl(fd.get(), VIDIOC_QUERY_EXT_CTRL, &q) != 0) {
      const int err = errno;
      if (err == EINVAL) break;  // past the last control
      return input_error("v4l2:" + device + ": VIDIOC_QUERY_EXT_CTRL failed: " + errno_text(err));
    }
    if (q.type != V4L2_CTRL_TYPE_CTRL_CLASS && (q.flags & V4L2_CTRL_FLAG_DISABLED) == 0) {
      V4l2Control c;
      c.id = q.id;
      c.name = c_string(q.name, sizeof q.name);
      c.minimum = q.minimum;
      c.maximum = q.maximum;
      c.default_value = q.default_value;
      c.is_button = q.type == V4L2_CTRL_TYPE_BUTTON;
      c.is_integer64 = q.type == V4L2_CTRL_TYPE_INTEGER64;
      c.read_only = (q.flags & V4L2_CTRL_FLAG_READ_ONLY) != 0;
      out.push_back(std::move(c));
    }
    q.id |= V4L2_CTRL_FLAG_NEXT_CTRL | V4L2_CTRL_FLAG_NEXT_COMPOUND;
  }
  return out;
}

Result<V4l2Control> find_v4l2_control(const std::vector<V4l2Control>& controls,
                                      std::string_view needle) {
  const std::string n = lower(needle);
  std::string names;
  for (const auto& c : controls) {
    if (lower(c.name).find(n) != std::string::npos) return c;
    names += (names.empty() ? "'" : ", '") + c.name + "'";
  }
  return input_error("no control named like '" + std::string(needle) + "' (controls: " + names +
                     ")");
}

Status set_v4l2_control(const std::string& device, const V4l2Control& control, std::int64_t value) {
  auto fd_or = open_node(device);
  if (!fd_or.is_ok()) return fd_or.status();
  FdGuard fd(fd_or.value());
  v4l2_ext_control c{};
  c.id = control.id;
  if (control.is_integer64) {
    c.value64 = value;
  } else {
    c.value = static_cast<std::int32_t>(value);
  }
  v4l2_ext_controls cs{};
  cs.which = V4L2_CTRL_WHICH_CUR_VAL;
  cs.count = 1;
  cs.controls = &c;
  if (xioctl(fd.get(), VIDIOC_S_EXT_CTRLS, &cs) != 0) {
    return input_error("v4l2:" + device + ": VIDIOC_S_EXT_CTRLS '" + control.name +
                       "' = " + std::to_string(value) + " failed: " + errno_text(errno));
  }
  return Status::ok();
}

}  // namespace mer::hal
