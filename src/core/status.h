#pragma once
/// @file status.h
/// Recoverable errors: a `Status` (code + message) and `Result<T>` (a value or a Status).
/// Library code never calls exit(); the application maps codes to process exit codes.

#include <string>
#include <utility>
#include <variant>

namespace mer {

/// Error categories; the application maps them to exit codes (see app/exit_codes.h).
enum class StatusCode {
  kOk = 0,
  kInvalidArgument,  ///< bad flag, bad config key or value (exit 2)
  kInputError,       ///< unreadable dataset, missing device, corrupt file (exit 3)
  kRuntimeError,     ///< failure while running (exit 4)
  kEndOfStream,      ///< a finite source has no more frames (not an error for callers)
  kTimeout,          ///< nothing arrived in time (retry)
  kUnavailable,      ///< feature not built in / not supported here
};

/// Success or an error with a human-readable message naming what failed.
class [[nodiscard]] Status {
 public:
  Status() = default;
  Status(StatusCode code, std::string message) : code_(code), message_(std::move(message)) {}

  /// The success value.
  static Status ok() { return {}; }
  /// True when the operation succeeded.
  bool is_ok() const { return code_ == StatusCode::kOk; }
  /// Error category.
  StatusCode code() const { return code_; }
  /// Message naming the file, key, frame or device involved.
  const std::string& message() const { return message_; }

 private:
  StatusCode code_ = StatusCode::kOk;
  std::string message_;
};

/// Shorthands for building errors.
inline Status invalid_argument(std::string m) {
  return {StatusCode::kInvalidArgument, std::move(m)};
}
inline Status input_error(std::string m) {
  return {StatusCode::kInputError, std::move(m)};
}
inline Status runtime_error(std::string m) {
  return {StatusCode::kRuntimeError, std::move(m)};
}

/// A value of type T or the Status explaining why there is none.
template <typename T>
class [[nodiscard]] Result {
 public:
  Result(T value) : v_(std::move(value)) {}         // NOLINT(google-explicit-constructor)
  Result(Status status) : v_(std::move(status)) {}  // NOLINT(google-explicit-constructor)

  /// True when a value is held.
  bool is_ok() const { return std::holds_alternative<T>(v_); }
  /// The value; only valid when is_ok().
  T& value() & { return std::get<T>(v_); }
  const T& value() const& { return std::get<T>(v_); }
  T&& value() && { return std::get<T>(std::move(v_)); }
  /// The error; Status::ok() when a value is held.
  Status status() const { return is_ok() ? Status::ok() : std::get<Status>(v_); }

 private:
  std::variant<T, Status> v_;
};

}  // namespace mer
