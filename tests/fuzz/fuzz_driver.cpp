// Replay driver for the fuzz targets when libFuzzer is not available (g++ builds, CTest):
// a main() that feeds LLVMFuzzerTestOneInput() every file of the seed corpus directories,
// then N deterministic pseudo-random mutations of them (bit flips, byte and 32-bit field
// overwrites with boundary values, truncation, deletion, insertion, duplication, splicing,
// text tokens). The same seed gives the same inputs on every machine (std::mt19937_64 is
// fully specified; no <random> distributions are used).
//
//   <target>_replay DIR... [--mutations N] [--seed S] [--max-len BYTES]
//                   [--only K] [--dump FILE]
//
// A crash prints the number of the input being run; `--only K --dump FILE` re-runs just
// that input and writes it to FILE (a reproducer for the libFuzzer binary or a debugger).

#include <unistd.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <csignal>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <random>
#include <string>
#include <string_view>
#include <vector>

// NOLINTNEXTLINE(readability-identifier-naming): the name libFuzzer calls
extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size);

namespace {

using Bytes = std::vector<std::uint8_t>;

constexpr std::size_t kDefaultMutations = 2000;
constexpr std::uint64_t kDefaultSeed = 1;
constexpr std::size_t kDefaultMaxLen = 16384;
constexpr std::size_t kMaxStackedMutations = 4;
constexpr std::size_t kMaxChunk = 64;  // bytes inserted/deleted/duplicated at once
constexpr int kMutationKinds = 10;
constexpr unsigned kBitsPerByte = 8;

constexpr std::array<std::uint32_t, 12> kInteresting32{
    0U,     1U,      2U,      0x7FU,       0x80U,       0xFFU,
    0x100U, 0x7FFFU, 0xFFFFU, 0x7FFFFFFFU, 0x80000000U, 0xFFFFFFFFU};
constexpr std::array<std::uint8_t, 6> kInteresting8{0x00, 0x01, 0x7F, 0x80, 0xFE, 0xFF};
constexpr std::array<std::string_view, 24> kTokens{"\n",
                                                   "\r\n",
                                                   " ",
                                                   "\t",
                                                   ",",
                                                   "#",
                                                   ":",
                                                   "[",
                                                   "]",
                                                   "0",
                                                   "-1",
                                                   "1e308",
                                                   "nan",
                                                   "inf",
                                                   "-0.0",
                                                   "1.5e-3",
                                                   "P0:",
                                                   "data:",
                                                   "resolution:",
                                                   "intrinsics:",
                                                   "T_BS:",
                                                   "1305031102.175304",
                                                   "99999999999999999999",
                                                   "rows: 4"};

volatile std::sig_atomic_t g_current = -1;

extern "C" void on_crash(int sig) {
  char buf[160];
  const int n = std::snprintf(buf, sizeof(buf),
                              "\nfuzz replay: crashed on input #%ld; reproduce with --only %ld "
                              "--dump FILE\n",
                              static_cast<long>(g_current), static_cast<long>(g_current));
  if (n > 0) static_cast<void>(::write(2, buf, static_cast<std::size_t>(n)));
  std::signal(sig, SIG_DFL);
  std::raise(sig);
}

class Mutator {
 public:
  Mutator(std::uint64_t seed, std::size_t max_len) : rng_(seed), max_len_(max_len) {}

  std::size_t below(std::size_t n) { return n == 0 ? 0 : static_cast<std::size_t>(rng_() % n); }

  void mutate(Bytes& b, const std::vector<Bytes>& corpus) {
    const std::size_t count = 1 + below(kMaxStackedMutations);
    for (std::size_t i = 0; i < count; ++i) mutate_once(b, corpus);
    if (b.size() > max_len_) b.resize(max_len_);
  }

 private:
  void mutate_once(Bytes& b, const std::vector<Bytes>& corpus) {
    switch (static_cast<int>(below(kMutationKinds))) {
      case 0:  // flip a bit
        if (!b.empty()) b[below(b.size())] ^= static_cast<std::uint8_t>(1U << below(kBitsPerByte));
        break;
      case 1:  // random byte
        if (!b.empty()) b[below(b.size())] = static_cast<std::uint8_t>(rng_());
        break;
      case 2:  // boundary byte
        if (!b.empty()) b[below(b.size())] = kInteresting8[below(kInteresting8.size())];
        break;
      case 3: {  // boundary 32-bit little-endian field, 4-byte aligned (the format's fields)
        if (b.size() < 4) break;
        const std::size_t at = below(b.size() / 4) * 4;
        const std::uint32_t v = kInteresting32[below(kInteresting32.size())];
        for (unsigned k = 0; k < 4; ++k) b[at + k] = static_cast<std::uint8_t>(v >> (8U * k));
        break;
      }
      case 4:  // truncate
        b.resize(below(b.size() + 1));
        break;
      case 5: {  // delete a range
        if (b.empty()) break;
        const std::size_t at = below(b.size());
        const std::size_t n = std::min(b.size() - at, 1 + below(kMaxChunk));
        b.erase(b.begin() + static_cast<std::ptrdiff_t>(at),
                b.begin() + static_cast<std::ptrdiff_t>(at + n));
        break;
      }
      case 6: {  // insert random bytes
        const std::size_t at = below(b.size() + 1);
        const std::size_t n = 1 + below(kMaxChunk);
        Bytes ins(n);
        for (auto& x : ins) x = static_cast<std::uint8_t>(rng_());
        b.insert(b.begin() + static_cast<std::ptrdiff_t>(at), ins.begin(), ins.end());
        break;
      }
      case 7: {  // duplicate a range (e.g. a chunk) elsewhere
        if (b.empty()) break;
        const std::size_t from = below(b.size());
        const std::size_t n = std::min(b.size() - from, 1 + below(kMaxChunk * 8));
        const Bytes piece(b.begin() + static_cast<std::ptrdiff_t>(from),
                          b.begin() + static_cast<std::ptrdiff_t>(from + n));
        const std::size_t at = below(b.size() + 1);
        b.insert(b.begin() + static_cast<std::ptrdiff_t>(at), piece.begin(), piece.end());
        break;
      }
      case 8: {  // splice: our head + another seed's tail
        const Bytes& other = corpus[below(corpus.size())];
        b.resize(below(b.size() + 1));
        const std::size_t from = below(other.size() + 1);
        b.insert(b.end(), other.begin() + static_cast<std::ptrdiff_t>(from), other.end());
        break;
      }
      default: {  // insert or overwrite a text token
        const std::string_view t = kTokens[below(kTokens.size())];
        const std::size_t at = below(b.size() + 1);
        if ((rng_() & 1U) != 0U || at + t.size() > b.size()) {
          b.insert(b.begin() + static_cast<std::ptrdiff_t>(at), t.begin(), t.end());
        } else {
          std::copy(t.begin(), t.end(), b.begin() + static_cast<std::ptrdiff_t>(at));
        }
        break;
      }
    }
  }

  std::mt19937_64 rng_;
  std::size_t max_len_;
};

Bytes read_file(const std::filesystem::path& p) {
  std::ifstream f(p, std::ios::binary);
  return {std::istreambuf_iterator<char>(f), std::istreambuf_iterator<char>()};
}

int usage(const char* argv0) {
  std::fprintf(stderr,
               "usage: %s DIR... [--mutations N] [--seed S] [--max-len BYTES] [--only K] "
               "[--dump FILE]\n",
               argv0);
  return 2;
}

}  // namespace

int main(int argc, char** argv) {
  std::vector<std::filesystem::path> dirs;
  std::size_t mutations = kDefaultMutations;
  std::uint64_t seed = kDefaultSeed;
  std::size_t max_len = kDefaultMaxLen;
  long only = -1;
  std::string dump;
  for (int i = 1; i < argc; ++i) {
    const std::string_view a = argv[i];
    const bool has_value = i + 1 < argc;
    if (a == "--mutations" && has_value) {
      mutations = std::strtoull(argv[++i], nullptr, 10);
    } else if (a == "--seed" && has_value) {
      seed = std::strtoull(argv[++i], nullptr, 10);
    } else if (a == "--max-len" && has_value) {
      max_len = std::strtoull(argv[++i], nullptr, 10);
    } else if (a == "--only" && has_value) {
      only = std::strtol(argv[++i], nullptr, 10);
    } else if (a == "--dump" && has_value) {
      dump = argv[++i];
    } else if (!a.empty() && a[0] == '-') {
      return usage(argv[0]);
    } else {
      dirs.emplace_back(a);
    }
  }
  if (dirs.empty()) return usage(argv[0]);

  std::vector<std::filesystem::path> files;
  for (const auto& d : dirs) {
    std::error_code ec;
    for (const auto& e : std::filesystem::directory_iterator(d, ec)) {
      if (e.is_regular_file()) files.push_back(e.path());
    }
    if (ec) {
      std::fprintf(stderr, "fuzz replay: cannot list %s: %s\n", d.c_str(), ec.message().c_str());
      return 2;
    }
  }
  std::sort(files.begin(), files.end());  // directory order is not deterministic
  if (files.empty()) {
    std::fprintf(stderr, "fuzz replay: no seed files in the corpus directories\n");
    return 2;
  }
  std::vector<Bytes> corpus;
  corpus.reserve(files.size());
  for (const auto& f : files) corpus.push_back(read_file(f));

  for (int sig : {SIGSEGV, SIGABRT, SIGBUS, SIGFPE, SIGILL}) std::signal(sig, on_crash);

  const auto t0 = std::chrono::steady_clock::now();
  Mutator mutator(seed, max_len);
  const long total = static_cast<long>(corpus.size() + mutations);
  Bytes input;
  for (long k = 0; k < total; ++k) {
    // Mutations are generated even when skipped (--only), so input #k is always the same.
    const auto ks = static_cast<std::size_t>(k);
    if (ks < corpus.size()) {
      input = corpus[ks];
    } else {
      input = corpus[mutator.below(corpus.size())];
      mutator.mutate(input, corpus);
    }
    if (only >= 0 && k != only) continue;
    if (!dump.empty()) {
      std::ofstream(dump, std::ios::binary)
          .write(reinterpret_cast<const char*>(input.data()),
                 static_cast<std::streamsize>(input.size()));
    }
    g_current = static_cast<std::sig_atomic_t>(k);
    LLVMFuzzerTestOneInput(input.data(), input.size());
    if (only >= 0) break;
  }
  const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  std::printf("fuzz replay: %zu seed files + %zu mutations (seed %llu) in %.2f s, no crash\n",
              corpus.size(), mutations, static_cast<unsigned long long>(seed), s);
  return 0;
}
