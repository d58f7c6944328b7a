// slamreloc_client: localize the images of a sequence with a `slamreloc serve` server.
//
//   slamreloc_client --server HOST:PORT [--map NAME] [--token T] [--tls-ca PEM]
//                    [--camera "MODEL W H ..."] [--timeout SECONDS] SEQUENCE
//
// --token (default: $SLAMRELOC_TOKEN, blanks around it dropped) is sent as `authorization:
// Bearer T`: at least 16 characters of printable ASCII without spaces, the server's rule;
// --tls-ca: connect with TLS, trusting the certificate(s) in that PEM file (else plain TCP).
// Every file named here is read as the Python side reads it: a regular file (a pipe, device or
// folder is refused, never opened blocking), of bounded size (PEM 1 MiB, an image 64 MiB).
//
// An option given twice is refused ("--camera is given twice: give it once"), as the Python CLI
// refuses it.
//
// SEQUENCE is a 7-Scenes sequence folder (frame-XXXXXX.color.png or .color.jpg, in name order)
// or a TUM RGB-D folder (rgb.txt: `timestamp rgb/file.png` lines, in the order listed, by the
// Python TUM reader's rules: UTF-8, lines ending at \n, fields separated by spaces or tabs and
// no other blank or line break; see plain_text_problem). Each image's file is sent as
// it is (the server decodes it) and one line is printed per image, as `slamreloc localize`
// prints it (with all the digits of a double):
//
//   NAME tx ty tz qx qy qz qw INLIERS     world_from_cam (camera-to-world; metres, x y z w)
//   # NAME: not localized (N inliers)
//
// Errors print `error: ...` on stderr and end with exit status 2: at once for a bad argument or
// sequence and for a failed call (server unreachable, unknown map, refused token, ...); an image
// that cannot be read or that the server refuses (BAD_IMAGE, TOO_LARGE) is reported and the
// other images are still localized, as `slamreloc localize` does.

#include <algorithm>
#include <chrono>
#include <cctype>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <iterator>
#include <map>
#include <memory>
#include <optional>
#include <regex>
#include <set>
#include <sstream>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <sys/stat.h>
#include <unistd.h>

#include <grpc/support/log.h>
#include <openssl/err.h>
#include <openssl/pem.h>
#include <openssl/x509.h>
#include <openssl/x509v3.h>
#include <grpcpp/grpcpp.h>

#include "relocalizer.grpc.pb.h"
#include "nonprintable.inc"

namespace fs = std::filesystem;
namespace v1 = slamreloc::v1;

// A bad argument, input or call: reported as `error: <what>`, exit status 2.
struct Error : std::runtime_error {
  using std::runtime_error::runtime_error;
};

// A failed call: its gRPC status and `kind`, the server's ErrorKind name (trailing metadata
// `slamreloc-error`), empty where the server did not answer (unreachable, deadline, size limit).
struct CallError : Error {
  CallError(const std::string& what, grpc::StatusCode code_, std::string kind_)
      : Error(what), code(code_), kind(std::move(kind_)) {}
  grpc::StatusCode code;
  std::string kind;
};

// What every call carries besides its request.
struct CallSettings {
  std::string map;    // empty: the only map the server serves
  std::string token;  // empty: none; else sent as `authorization: Bearer <token>`
  std::chrono::milliseconds timeout{60000};
};

namespace {

const char* code_name(grpc::StatusCode code) {
  static const char* const names[] = {  // grpc::StatusCode 0 to 16
      "OK", "CANCELLED", "UNKNOWN", "INVALID_ARGUMENT", "DEADLINE_EXCEEDED", "NOT_FOUND",
      "ALREADY_EXISTS", "PERMISSION_DENIED", "RESOURCE_EXHAUSTED", "FAILED_PRECONDITION",
      "ABORTED", "OUT_OF_RANGE", "UNIMPLEMENTED", "INTERNAL", "UNAVAILABLE", "DATA_LOSS",
      "UNAUTHENTICATED"};
  const int i = static_cast<int>(code);
  return i >= 0 && i < static_cast<int>(std::size(names)) ? names[i] : "UNKNOWN_CODE";
}

constexpr std::size_t kMinToken = 16;                 // the server's rule (`token_problem`)
constexpr std::size_t kMaxMapName = 128;              // characters (`MAX_MAP_NAME`)
constexpr std::uintmax_t kMaxPemBytes = 1u << 20;      // slamreloc.io.pem.MAX_PEM_BYTES
constexpr std::uintmax_t kMaxImageBytes = 64u << 20;   // the client's gRPC message bound
constexpr std::uintmax_t kMaxListBytes = 1u << 30;     // rgb.txt, as the Python TUM reader
constexpr double kMinTimeoutS = 0.001, kMaxTimeoutS = 1e6;  // proto.messages.CLIENT_TIMEOUT_S
constexpr double kMaxStampS = 1e12;  // slamreloc.geometry.MAX_STAMP_S
constexpr double kStampToleranceS = 1e-6;  // slamreloc.geometry.STAMP_TOLERANCE_S

std::string one_line(std::string text) {
  std::replace(text.begin(), text.end(), '\n', ' ');
  std::replace(text.begin(), text.end(), '\r', ' ');
  return text;
}

}  // namespace

// One Localize call: the image file's bytes (JPEG, PNG, ...) and, optionally, its camera (else
// the server uses the map's camera scaled to the image). Throws CallError when the call fails.
v1::LocalizeResponse localize(v1::Relocalizer::StubInterface& stub, const std::string& image_bytes,
                              const v1::Camera* camera, const CallSettings& settings) {
  v1::LocalizeRequest request;
  request.set_map(settings.map);
  request.mutable_image()->set_encoded(image_bytes);
  if (camera != nullptr) *request.mutable_camera() = *camera;

  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() + settings.timeout);
  if (!settings.token.empty()) context.AddMetadata("authorization", "Bearer " + settings.token);
  v1::LocalizeResponse response;
  const grpc::Status status = stub.Localize(&context, request, &response);
  if (status.ok()) return response;

  std::string kind;
  const auto& trailers = context.GetServerTrailingMetadata();
  if (auto it = trailers.find("slamreloc-error"); it != trailers.end())
    kind.assign(it->second.data(), it->second.size());
  std::string what = code_name(status.error_code());
  if (!kind.empty()) what += " (" + kind + ")";
  if (!status.error_message().empty()) what += ": " + one_line(status.error_message());
  throw CallError(what, status.error_code(), kind);
}

// The tracking-loss hook: what a SLAM system calls when its own tracking is lost. It is the
// same Localize call; it returns world_from_cam (camera-to-world, the slamreloc map's frame), or
// nothing when the image was not localized (too few keypoints or inliers). A failed call throws
// CallError.
//
// In ORB-SLAM3's Tracking::Track(), branch mState == RECENTLY_LOST (visual), after its own
// relocalization failed (an untested sketch; README.md says what the two helpers must do):
//
//   bOK = Relocalization();
//   if (!bOK) {
//     std::vector<uchar> png;
//     cv::imencode(".png", mImGray, png);
//     if (auto pose = relocalize(*stub, std::string(png.begin(), png.end()), &camera, settings)) {
//       mCurrentFrame.SetPose(TcwInOrbFrame(*pose));  // inverse, times the maps' transform
//       bOK = MatchMapPointsByProjection(mCurrentFrame);  // + PoseOptimization, >= 50 inliers
//     }
//   }
//   // ... Track() then runs TrackLocalMap() when bOK
std::optional<v1::Transform> relocalize(v1::Relocalizer::StubInterface& stub,
                                        const std::string& image_bytes, const v1::Camera* camera,
                                        const CallSettings& settings = {}) {
  const v1::LocalizeResponse response = localize(stub, image_bytes, camera, settings);
  if (!response.localized()) return std::nullopt;
  return response.world_from_cam();
}

namespace {

// Why `token` cannot be sent (empty when it can): the server's rule, at least kMinToken
// characters of printable ASCII without spaces (what gRPC metadata carries).
std::string token_problem(const std::string& token) {
  if (token.size() < kMinToken)
    return "must have at least " + std::to_string(kMinToken) + " characters";
  for (const unsigned char c : token)
    if (c < 0x21 || c > 0x7E)
      return "must be printable ASCII without spaces or line breaks (gRPC metadata carries "
             "nothing else)";
  return "";
}

// `text` as given, for a message: in quotes, its first 80 bytes, bytes that are not printable
// ASCII as \xHH (a name may hold anything; the terminal must not take it as commands).
std::string shown(const std::string& text) {
  static const char* hex = "0123456789abcdef";
  std::string out = "'";
  for (std::size_t i = 0; i < text.size() && i < 80; ++i) {
    const unsigned char c = text[i];
    if (c >= 0x20 && c < 0x7F && c != '\\' && c != '\'') {
      out += static_cast<char>(c);
    } else {
      out += "\\x";
      out += hex[c >> 4];
      out += hex[c & 0xF];
    }
  }
  return out + (text.size() > 80 ? "'..." : "'");
}

// The length in bytes of the UTF-8 character that starts at text[i], its code point in `cp`;
// 0 where the bytes there are not UTF-8 by Python's strict decoder (cut short, an overlong
// form, a surrogate, beyond U+10FFFF), which then reports byte i.
int utf8_char(const std::string& text, std::size_t i, char32_t& cp) {
  const unsigned char c = text[i];
  const int n = c < 0x80            ? 1
                : (c >> 5) == 0x6   ? 2
                : (c >> 4) == 0xE   ? 3
                : (c >> 3) == 0x1E  ? 4
                                    : 0;
  if (n == 0 || i + n > text.size()) return 0;
  cp = n == 1 ? c : c & (0x7F >> n);
  for (int k = 1; k < n; ++k) {
    const unsigned char cc = text[i + k];
    if ((cc >> 6) != 0x2) return 0;
    cp = (cp << 6) | (cc & 0x3F);
  }
  const char32_t least[] = {0, 0, 0x80, 0x800, 0x10000};
  if (cp < least[n] || cp > 0x10FFFF || (cp >= 0xD800 && cp <= 0xDFFF)) return 0;
  return n;
}

// Whether Python's str.isprintable() takes the code point `cp` (nonprintable.inc's table):
// every name rule of the server is built on it.
bool printable(char32_t cp) {
  const auto* end = kNonPrintable + kNonPrintableRuns;
  const auto* run = std::upper_bound(kNonPrintable, end, cp,
                                     [](char32_t c, const char32_t(&r)[2]) { return c < r[0]; });
  return run == kNonPrintable || cp > run[-1][1];
}

// Why `name` cannot name a served map (empty when it can): the server's rule
// (`map_name_problem`): valid UTF-8, 1 to kMaxMapName characters, all printable by Python's
// rule and none a space. (Its composed-form rule is left to the server.)
std::string map_name_problem(const std::string& name) {
  if (name.empty()) return "is empty (give a map name, or leave --map out)";
  std::size_t chars = 0;
  for (std::size_t i = 0; i < name.size(); ++chars) {
    char32_t cp = 0;
    const int n = utf8_char(name, i, cp);
    if (n == 0) return "is not valid UTF-8 text";
    if (cp == ' ' || !printable(cp)) return "holds a control, format or space character: printable characters "
                    "without spaces only";
    i += n;
  }
  if (chars > kMaxMapName)
    return "has " + std::to_string(chars) + " characters, more than " +
           std::to_string(kMaxMapName);
  return "";
}

// `text` without the blanks (spaces, tabs, line breaks) around it.
std::string strip_blanks(const std::string& text) {
  const char* blanks = " \t\r\n\v\f";
  const auto first = text.find_first_not_of(blanks);
  if (first == std::string::npos) return "";
  return text.substr(first, text.find_last_not_of(blanks) - first + 1);
}

// Closes a file descriptor when it goes out of scope.
struct Fd {
  int fd;
  ~Fd() {
    if (fd >= 0) ::close(fd);
  }
};

// The bytes of the regular file `path` (`what` names it in errors), at most `limit` of them.
// Opened without blocking and checked on what was opened, as slamreloc.io.fileio.open_regular
// does: a named pipe with no writer would block for ever, a device would be read for ever.
std::string read_file(const fs::path& path, const std::string& what, std::uintmax_t limit) {
  const std::string name = path.string() + ": " + what;
  Fd file{::open(path.c_str(), O_RDONLY | O_NONBLOCK | O_NOCTTY | O_CLOEXEC)};
  if (file.fd < 0)
    throw Error(errno == ENOENT ? name + " file not found"
                                : name + " cannot be read (" + std::strerror(errno) + ")");
  struct stat info {};
  if (::fstat(file.fd, &info) != 0) throw Error(name + " cannot be read");
  if (!S_ISREG(info.st_mode)) {
    const char* kind = S_ISDIR(info.st_mode)                              ? "a folder"
                       : S_ISFIFO(info.st_mode)                           ? "a named pipe"
                       : S_ISCHR(info.st_mode) || S_ISBLK(info.st_mode)   ? "a device"
                       : S_ISSOCK(info.st_mode)                           ? "a socket"
                                                                          : "not a file";
    throw Error(name + " is not a regular file (" + kind + ")");
  }
  const auto too_large = [&](const std::string& size) {
    return Error(name + " file of " + size + ", over the " + std::to_string(limit >> 20) +
                 " MiB such a file may hold");
  };
  if (static_cast<std::uintmax_t>(info.st_size) > limit)
    throw too_large(std::to_string(info.st_size) + " bytes");
  ::fcntl(file.fd, F_SETFL, ::fcntl(file.fd, F_GETFL) & ~O_NONBLOCK);
  std::string bytes;
  char buffer[1 << 16];
  for (;;) {  // a file growing while read is bounded too
    const ssize_t n = ::read(file.fd, buffer, sizeof buffer);
    if (n < 0 && errno == EINTR) continue;
    if (n < 0) throw Error(name + " cannot be read (" + std::strerror(errno) + ")");
    if (n == 0) break;
    bytes.append(buffer, static_cast<std::size_t>(n));
    if (bytes.size() > limit) throw too_large("more than " + std::to_string(limit) + " bytes");
  }
  return bytes;
}

// The number rule of slamreloc.io.numbers: a plain ASCII decimal (-1.5, 2e-3; no hex, blanks
// or words), finite; `what` names it in the error.
double parse_number(const std::string& text, const std::string& what) {
  static const std::regex decimal(R"([+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?)");
  if (text.size() > 400 || !std::regex_match(text, decimal))
    throw Error(what + ": '" + text.substr(0, 40) +
                "' is not a number (numbers are plain ASCII decimals such as -1.5 or 2e-3)");
  const double value = std::strtod(text.c_str(), nullptr);
  if (!std::isfinite(value)) throw Error(what + ": " + text.substr(0, 40) + " is not finite");
  return value;
}

// Why `target` (--server) cannot be connected to, empty when it can: HOST:PORT with a host of
// plain ASCII without blanks (no short, octal or hexadecimal IPv4 form, which libraries read
// differently) and a decimal port from 1 to 65535 (gRPC would wrap 65537 to 1); a target with
// a scheme (dns:, unix:, ...) is left to gRPC. slamreloc.io.address.target_problem's rule.
std::string target_problem(const std::string& target) {
  static const char* const schemes[] = {"dns", "unix", "unix-abstract", "ipv4", "ipv6",
                                        "vsock"};
  const std::string head = target.substr(0, target.find(':'));
  if (target.find("://") != std::string::npos ||
      std::find(std::begin(schemes), std::end(schemes), head) != std::end(schemes))
    return "";
  const auto colon = target.rfind(':');
  if (colon == std::string::npos || colon == 0) return "is not HOST:PORT";
  std::string host = target.substr(0, colon);
  const std::string port = target.substr(colon + 1);
  for (const unsigned char c : host)
    if (c < 0x21 || c > 0x7E)
      return "host holds a blank or a character beyond plain ASCII (write 127.0.0.1, ::1, a "
             "name; IDNA xn-- for other scripts)";
  if (host.size() > 2 && host.front() == '[' && host.back() == ']')
    host = host.substr(1, host.size() - 2);
  in_addr v4{};
  if (::inet_aton(host.c_str(), &v4) != 0 && ::inet_pton(AF_INET, host.c_str(), &v4) != 1)
    return "host is a short, octal or hexadecimal IPv4 form, which libraries read "
           "differently: write four decimal numbers (127.0.0.1)";
  const bool digits = !port.empty() && port.size() <= 5 &&
                      std::all_of(port.begin(), port.end(),
                                  [](char c) { return c >= '0' && c <= '9'; });
  if (!digits || std::stol(port) < 1 || std::stol(port) > 65535)
    return "port '" + port.substr(0, 40) + "' is not a number from 1 to 65535";
  return "";
}

struct Options {
  std::string server;
  fs::path tls_ca;     // empty: plain TCP
  std::string camera;  // a COLMAP camera line without its id; empty: the map's camera
  CallSettings call;
  fs::path sequence;
};

const char kUsage[] =
    "usage: slamreloc_client --server HOST:PORT [--map NAME] [--token T] [--tls-ca PEM]\n"
    "                        [--camera \"PINHOLE W H fx fy cx cy\"] [--timeout SECONDS] SEQUENCE\n"
    "--token defaults to $SLAMRELOC_TOKEN\n"
    "SEQUENCE: a 7-Scenes sequence folder (frame-XXXXXX.color.png) or a TUM RGB-D folder "
    "(rgb.txt)\n"
    "prints `NAME tx ty tz qx qy qz qw INLIERS` (world_from_cam) or "
    "`# NAME: not localized (N inliers)` per image\n";

Options parse_args(int argc, char** argv) {
  Options opts;
  std::string token_source;  // where the token came from, for its error
  if (const char* token = std::getenv("SLAMRELOC_TOKEN")) {
    opts.call.token = strip_blanks(token);
    token_source = "$SLAMRELOC_TOKEN";
    if (opts.call.token.empty())
      throw Error("$SLAMRELOC_TOKEN is empty (give a token, or unset it)");
  }
  // an option given twice is refused (which value was meant?) before any value is read: the
  // Python CLI's rule and message (slamreloc.cli), `--server=X` and `--server X` alike
  static const char* const options[] = {"--server", "--map", "--token", "--tls-ca", "--camera",
                                        "--timeout"};
  std::set<std::string> given;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    const std::string name = arg.substr(0, arg.find('='));
    if (std::find(std::begin(options), std::end(options), name) == std::end(options)) continue;
    if (!given.insert(name).second) throw Error(name + " is given twice: give it once");
    if (name.size() == arg.size()) ++i;  // its value is the next argument
  }
  std::vector<std::string> positional;
  for (int i = 1; i < argc; ++i) {
    std::string arg = argv[i];
    if (arg == "-h" || arg == "--help") {
      std::cout << kUsage;
      std::exit(0);
    }
    if (arg.rfind("--", 0) != 0 || arg == "--") {
      positional.push_back(arg);
      continue;
    }
    std::string value;
    if (auto eq = arg.find('='); eq != std::string::npos) {
      value = arg.substr(eq + 1);
      arg.resize(eq);
    } else if (i + 1 < argc) {
      value = argv[++i];
    } else {
      throw Error(arg + ": needs a value");
    }
    if (arg == "--server") {
      const std::string problem = target_problem(value);
      if (!problem.empty()) throw Error("--server '" + value.substr(0, 80) + "' " + problem);
      opts.server = value;
    } else if (arg == "--map") {
      const std::string problem = map_name_problem(value);
      if (!problem.empty()) throw Error("--map " + shown(value) + " " + problem);
      opts.call.map = value;
    } else if (arg == "--token") {
      opts.call.token = strip_blanks(value);
      token_source = "--token";
      if (opts.call.token.empty()) throw Error("--token: empty (give a token, or leave it out)");
    } else if (arg == "--tls-ca") {
      if (value.empty()) throw Error("--tls-ca: empty (give a PEM file, or leave it out)");
      opts.tls_ca = value;
    } else if (arg == "--camera") {
      opts.camera = strip_blanks(value);
      if (opts.camera.empty())
        throw Error("--camera: empty (give a COLMAP camera line such as \"PINHOLE W H fx fy cx "
                    "cy\", or leave it out for the map's camera)");
    } else if (arg == "--timeout") {
      const double seconds = parse_number(value, "--timeout");
      if (!(seconds >= kMinTimeoutS && seconds <= kMaxTimeoutS))
        throw Error("--timeout: " + value + " seconds, out of 0.001 to 1e6 (the Python "
                    "client's `timeout_s` rule)");
      opts.call.timeout = std::chrono::milliseconds(static_cast<long long>(seconds * 1000));
    } else {
      throw Error(arg + ": unknown option (see --help)");
    }
  }
  if (!opts.call.token.empty()) {
    const std::string problem = token_problem(opts.call.token);
    if (!problem.empty()) throw Error("the token (" + token_source + ") " + problem);
  }
  if (opts.server.empty()) throw Error("--server HOST:PORT is required (see --help)");
  if (positional.size() != 1) throw Error("give one SEQUENCE folder (see --help)");
  opts.sequence = positional[0];
  return opts;
}

// Why the UTF-8 `text` breaks the plain line rule of TUM's lists, from byte `start` on (empty
// when it does not; `line` is then the line number of what breaks it): a carriage return not
// followed by a line feed, or a blank or line break other than a space, a tab and a line feed
// (\v, \f, 0x1c-0x1f, U+0085, U+00A0, U+1680, U+2000-U+200A, U+2028, U+2029, U+202F, U+205F,
// U+3000: every character Python's str.isspace takes besides those). Other characters (other
// control characters included) belong to their field. slamreloc.io.fileio.plain_lines's rule,
// in the same words.
std::string plain_text_problem(const std::string& text, std::size_t start, std::size_t& line) {
  line = 1;
  for (std::size_t i = start; i < text.size();) {
    char32_t cp = 0;
    const int n = utf8_char(text, i, cp);  // the text was checked as UTF-8
    const bool lone_cr = cp == 0x0D && (i + 1 >= text.size() || text[i + 1] != '\n');
    const bool blank = cp == 0x0B || cp == 0x0C || (cp >= 0x1C && cp <= 0x1F) || cp == 0x85 ||
                       cp == 0xA0 || cp == 0x1680 || (cp >= 0x2000 && cp <= 0x200A) ||
                       cp == 0x2028 || cp == 0x2029 || cp == 0x202F || cp == 0x205F ||
                       cp == 0x3000;
    if (lone_cr || blank) {
      char code[16];
      std::snprintf(code, sizeof code, "U+%04X", static_cast<unsigned>(cp));
      return std::string(lone_cr ? "a carriage return not followed by a line feed"
                                 : "a blank or line break other than a space, a tab or a line "
                                   "feed") +
             " (" + code + "): fields are separated by spaces or tabs only, lines end at a line "
                           "feed (or CR LF)";
    }
    if (cp == '\n') ++line;
    i += n == 0 ? 1 : n;
  }
  return "";
}

// Why `name`, a TUM image's file stem, cannot name a frame (empty when it can): the Python
// datasets' rule (slamreloc.types.frame_name_problem): not empty, every character printable
// by Python's rule or a space (no control, format, private-use or unassigned character, no
// other blank), not absolute, and, a backslash read as a slash, no '..', no empty or '.' part.
std::string frame_name_problem(const std::string& name) {
  if (name.empty()) return "is empty";
  for (std::size_t i = 0; i < name.size();) {
    char32_t cp = 0;
    const int n = utf8_char(name, i, cp);  // the list was checked as UTF-8
    if (cp != ' ' && !printable(cp))
      return "holds a line break or another control character";
    i += n == 0 ? 1 : n;
  }
  std::string slashed = name;
  std::replace(slashed.begin(), slashed.end(), '\\', '/');
  std::vector<std::string> parts;
  for (std::size_t start = 0;;) {
    const std::size_t slash = slashed.find('/', start);
    parts.push_back(slashed.substr(start, slash == std::string::npos ? slash : slash - start));
    if (slash == std::string::npos) break;
    start = slash + 1;
  }
  const auto has = [&](const char* part) {
    return std::find(parts.begin(), parts.end(), part) != parts.end();
  };
  if (name.front() == '/' || has(".."))
    return "is not a path inside the dataset (absolute, or with '..')";
  if (has("") || has("."))
    return "is not a plain relative path (an empty or '.' part, as in 'a//b' or 'a/./b')";
  return "";
}

// The fields of `line`, separated by spaces and tabs.
std::vector<std::string> plain_fields(const std::string& line) {
  std::vector<std::string> fields;
  for (std::size_t i = line.find_first_not_of(" \t"); i != std::string::npos;) {
    const std::size_t end = line.find_first_of(" \t", i);
    fields.push_back(line.substr(i, end == std::string::npos ? std::string::npos : end - i));
    i = end == std::string::npos ? end : line.find_first_not_of(" \t", end);
  }
  return fields;
}

// The images of a 7-Scenes sequence folder (name order) or a TUM RGB-D folder (rgb.txt order).
std::vector<fs::path> sequence_images(const fs::path& dir) {
  std::error_code ec;
  if (!fs::is_directory(dir, ec))
    throw Error(dir.string() + (fs::exists(dir, ec) ? ": not a folder" : ": no such folder"));
  std::vector<fs::path> images;
  const fs::path list = dir / "rgb.txt";
  if (fs::exists(list, ec)) {  // rgb.txt: slamreloc.datasets.tum's rules
    // read as slamreloc.io.fileio.read_text reads text (UTF-8, no NUL byte, a leading
    // byte-order mark dropped), its lines and fields by plain_lines's rule
    const std::string text = read_file(list, "image list", kMaxListBytes);
    for (std::size_t i = 0; i < text.size();) {
      char32_t cp = 0;
      const int n = utf8_char(text, i, cp);
      if (n == 0)
        throw Error(list.string() + ": image list is not UTF-8 text (byte " + std::to_string(i) +
                    ")");
      i += n;
    }
    const auto nul = text.find('\0');
    if (nul != std::string::npos)  // the Python readers' rule: no text file holds one
      throw Error(list.string() + ":" +
                  std::to_string(1 + std::count(text.begin(), text.begin() + nul, '\n')) +
                  ": image list holds a NUL byte (byte " + std::to_string(nul) +
                  "); text files have none");
    const std::size_t start = text.rfind("\xEF\xBB\xBF", 0) == 0 ? 3 : 0;
    std::size_t bad_line = 0;
    const std::string problem = plain_text_problem(text, start, bad_line);
    if (!problem.empty())
      throw Error(list.string() + ":" + std::to_string(bad_line) + ": image list holds " +
                  problem);
    std::map<double, std::pair<int, std::string>> seen;  // stamp -> (first line, its file)
    std::set<std::string> stems;
    double last_t = 0;  // the latest stamp so far, on line last_n (0: none yet)
    int last_n = 0;
    int n = 0;
    for (std::size_t pos = start; pos < text.size();) {
      std::size_t nl = text.find('\n', pos);
      if (nl == std::string::npos) nl = text.size();
      std::string line = text.substr(pos, nl - pos);
      pos = nl + 1;
      ++n;
      if (!line.empty() && line.back() == '\r') line.pop_back();
      const std::string where = list.string() + ":" + std::to_string(n);
      const std::vector<std::string> fields = plain_fields(line);
      if (fields.empty() || fields[0][0] == '#') continue;  // blank line or comment
      if (fields.size() != 2)
        throw Error(where + ": expected 2 fields, got " + std::to_string(fields.size()));
      const std::string& stamp = fields[0];
      const std::string& file = fields[1];
      const double t = parse_number(stamp, where + ": timestamp");
      if (std::fabs(t) > kMaxStampS)
        throw Error(where + ": timestamp " + stamp + " is beyond 1e12 s: timestamps are seconds");
      const fs::path rel(file);
      if (rel.is_absolute() || std::find(rel.begin(), rel.end(), "..") != rel.end())
        throw Error(where + ": '" + file.substr(0, 80) + "' points outside the dataset folder");
      // stamps within kStampToleranceS are one instant, as every Python reader has it
      const auto first = seen.lower_bound(t - kStampToleranceS);
      if (first != seen.end() && first->first <= t + kStampToleranceS) {
        if (first->second.second != file)
          throw Error(where + ": timestamp " + stamp +
                      (first->first == t ? " repeats line " : " is within 1 microsecond of line ") +
                      std::to_string(first->second.first) + " with another file");
        continue;  // the same row twice: read once
      }
      seen.emplace(t, std::make_pair(n, file));
      if (last_n > 0 && t < last_t)
        throw Error(where + ": timestamp " + stamp + " is earlier than line " +
                    std::to_string(last_n) + "'s; the frames must be listed in time order");
      last_t = t;
      last_n = n;
      const std::string stem = rel.stem().string();  // the frame's name, as Python's
      const std::string name_problem = frame_name_problem(stem);
      if (!name_problem.empty())
        throw Error(where + ": frame name " + shown(stem) + " " + name_problem +
                    ": its name comes from the file's name; rename it");
      if (!stems.insert(stem).second)
        throw Error(list.string() + ": image '" + rel.stem().string() +
                    "' is listed more than once");
      images.push_back(dir / rel);
    }
  } else {
    for (const auto& entry : fs::directory_iterator(dir, ec)) {
      const std::string name = entry.path().filename().string();
      const auto ends_with = [&](const std::string& tail) {
        return name.size() > tail.size() &&
               name.compare(name.size() - tail.size(), tail.size(), tail) == 0;
      };
      if (name.rfind("frame-", 0) == 0 && (ends_with(".color.png") || ends_with(".color.jpg")))
        images.push_back(entry.path());
    }
    if (ec) throw Error(dir.string() + ": cannot be listed (" + ec.message() + ")");
    std::sort(images.begin(), images.end());
  }
  if (images.empty())
    throw Error(dir.string() + ": no images (neither frame-*.color.png nor rgb.txt)");
  return images;
}

// --tls-ca's PEM rule, the one slamreloc.io.pem.certificates_der states (read there), so that
// both clients refuse the same files: lines end at "\n" (then "\r" and trailing blanks are
// dropped); no control character but a tab; text outside blocks is skipped;
// "-----BEGIN LABEL-----" opens a block that "-----END LABEL-----" must close; a marker after
// other text is refused; a body is base64 lines of at most 76 characters, no blank line, no
// "Name: value" headers; blocks of other labels are otherwise skipped; a TRUSTED CERTIFICATE
// is refused; a certificate block decodes to one X.509 certificate (version 1 or 3) in
// strict DER, its extensions readable and each given once; the file holds at least one.
bool ascii_space(char c) {
  return c == ' ' || c == '\t' || c == '\n' || c == '\r' || c == '\v' || c == '\f';
}

std::string without_blanks(const std::string& text) {
  std::string out;
  for (char c : text)
    if (!ascii_space(c)) out += c;
  return out;
}

// The bytes of base64 `text` (blanks removed already); nullopt where it is not base64: other
// characters, padding anywhere but at the end or over two, a length not a multiple of 4.
std::optional<std::string> base64_bytes(const std::string& text) {
  static const std::string alphabet =
      "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
  const size_t data_end = text.find_last_not_of('=') + 1;
  const size_t padding = text.size() - data_end;
  if (text.empty() || text.size() % 4 != 0 || padding > 2) return std::nullopt;
  std::string out;
  unsigned value = 0;
  int bits = 0;
  for (size_t i = 0; i < data_end; ++i) {
    const size_t digit = alphabet.find(text[i]);
    if (digit == std::string::npos) return std::nullopt;
    value = (value << 6) | static_cast<unsigned>(digit);
    bits += 6;
    if (bits >= 8) {
      bits -= 8;
      out += static_cast<char>((value >> bits) & 0xFF);
    }
  }
  return out;
}

bool starts_with(const std::string& s, const std::string& prefix) {
  return s.compare(0, prefix.size(), prefix) == 0;
}

// The LABEL of a marker line "PREFIX LABEL-----" (ASCII letters, digits and spaces).
std::optional<std::string> marker_label(const std::string& line, const std::string& prefix) {
  const std::string rest = line.substr(prefix.size());
  if (rest.size() <= 5 || rest.compare(rest.size() - 5, 5, "-----") != 0) return std::nullopt;
  const std::string label = rest.substr(0, rest.size() - 5);
  bool any = false;
  for (char c : label) {
    if (c == ' ') continue;
    if (!std::isalnum(static_cast<unsigned char>(c)) || static_cast<unsigned char>(c) > 127)
      return std::nullopt;
    any = true;
  }
  if (!any) return std::nullopt;
  return label;
}

// Whether a UTCTime (YYMMDDHHMMSSZ) or GeneralizedTime (YYYYMMDDHHMMSSZ) is a real instant
// written as DER writes it.
bool der_time(const unsigned char* v, size_t size, bool generalized) {
  const size_t digits = generalized ? 14 : 12;
  if (size != digits + 1 || v[digits] != 'Z') return false;
  for (size_t i = 0; i < digits; ++i)
    if (v[i] < '0' || v[i] > '9') return false;
  auto at = [&](size_t i) { return (v[i] - '0') * 10 + (v[i + 1] - '0'); };
  const size_t o = generalized ? 2 : 0;
  int year = generalized ? at(0) * 100 + at(2) : at(0) + (at(0) < 50 ? 2000 : 1900);
  const int month = at(2 + o), day = at(4 + o);
  const bool leap = (year % 4 == 0 && year % 100 != 0) || year % 400 == 0;
  const int days[] = {31, leap ? 29 : 28, 31, 30, 31, 30, 31, 31, 30, 31, 30, 31};
  return month >= 1 && month <= 12 && day >= 1 && day <= days[month - 1] && at(6 + o) <= 23 &&
         at(8 + o) <= 59 && at(10 + o) <= 59;
}

// Whether a BIT STRING's value breaks DER: unused bits over 7, or not 0.
bool bit_string_problem(const unsigned char* value, size_t size) {
  return size == 0 || value[0] > 7 || (size == 1 && value[0] != 0) ||
         (size > 1 && (value[size - 1] & ((1u << value[0]) - 1)));
}

// Why the DER elements in [p, end) break a rule of DER that OpenSSL's reader lets through
// (it keeps a certificate's signed part as received), or "": a length not in its shortest
// form (or indefinite), a BOOLEAN other than 0xFF (a FALSE is a DEFAULT, which DER leaves
// out), an INTEGER with a redundant leading byte, a time without its seconds and Z.
// Constructed elements are read through, at most `depth` levels deep.
std::string der_problem(const unsigned char* p, const unsigned char* end, int depth) {
  if (depth <= 0) return "nested too deeply";
  while (p < end) {
    const unsigned char tag = *p++;
    if ((tag & 0x1F) == 0x1F) return "a tag in the long form";
    if (p >= end) return "an element cut short";
    size_t size = *p++;
    if (size == 0x80) return "an indefinite length";
    if (size > 0x80) {
      const size_t bytes = size & 0x7F;
      if (bytes > 4 || static_cast<size_t>(end - p) < bytes) return "a length cut short";
      if (*p == 0) return "a length not in its shortest form";
      size = 0;
      for (size_t i = 0; i < bytes; ++i) size = (size << 8) | *p++;
      if (size < 0x80) return "a length not in its shortest form";
    }
    if (size > static_cast<size_t>(end - p)) return "an element cut short";
    const unsigned char* value = p;
    p += size;
    if ((tag & 0x20) && (tag & 0xC0) == 0 && tag != 0x30 && tag != 0x31) {
      return "a string written in constructed form";
    } else if (tag & 0x20) {
      const std::string inner = der_problem(value, p, depth - 1);
      if (!inner.empty()) return inner;
    } else if (tag == 0x03 && bit_string_problem(value, size)) {
      return "a BIT STRING whose unused bits are not 0";
    } else if ((tag == 0x17 || tag == 0x18) && !der_time(value, size, tag == 0x18)) {
      return "a time not a real instant written with its seconds and Z";
    } else if (tag == 0x01 && (size != 1 || value[0] != 0xFF)) {
      return size == 1 && value[0] == 0 ? "a BOOLEAN FALSE written out, which DER leaves out"
                                        : "a BOOLEAN TRUE not written as 0xFF";
    } else if (tag == 0x02 && (size == 0 || (size > 1 && ((value[0] == 0 && !(value[1] & 0x80)) ||
                                                         (value[0] == 0xFF && (value[1] & 0x80)))))) {
      return "an INTEGER not in its shortest form";
    }
  }
  return "";
}

// One DER element in [p, end) whose lengths der_problem has checked: its tag and value.
struct Element {
  unsigned char tag;
  const unsigned char* value;
  const unsigned char* end;
};
std::optional<Element> element_at(const unsigned char* p, const unsigned char* end) {
  if (end - p < 2) return std::nullopt;
  const unsigned char tag = p[0];
  size_t size = p[1];
  p += 2;
  if (size & 0x80) {
    const size_t bytes = size & 0x7F;
    if (bytes > 4 || static_cast<size_t>(end - p) < bytes) return std::nullopt;
    size = 0;
    for (size_t i = 0; i < bytes; ++i) size = (size << 8) | *p++;
  }
  if (size > static_cast<size_t>(end - p)) return std::nullopt;
  return Element{tag, p, p + size};
}

// Why parts of a certificate that der_problem reads as plain bytes break DER, or "": the
// unique IDs ([1] and [2] of the signed part: BIT STRINGs) and each extension's value (DER
// inside its OCTET STRING). slamreloc.io.pem.certificate_parts_problem's rule.
std::string certificate_parts_problem(const unsigned char* start, const unsigned char* end) {
  const auto whole = element_at(start, end);
  if (!whole) return "";
  const auto tbs = element_at(whole->value, whole->end);
  if (!tbs) return "";
  for (auto part = element_at(tbs->value, tbs->end); part; part = element_at(part->end, tbs->end)) {
    if ((part->tag == 0x81 || part->tag == 0x82) &&
        bit_string_problem(part->value, part->end - part->value))
      return "a unique ID whose unused bits are not 0";
    if (part->tag != 0xA3) continue;
    const auto listed = element_at(part->value, part->end);
    if (!listed) return "";
    for (auto one = element_at(listed->value, listed->end); one;
         one = element_at(one->end, listed->end)) {
      std::optional<Element> last;
      for (auto field = element_at(one->value, one->end); field;
           field = element_at(field->end, one->end))
        last = field;
      if (!last || last->tag != 0x04) continue;
      const std::string problem = der_problem(last->value, last->end, 32);
      if (!problem.empty()) return "an extension's value holds " + problem;
    }
  }
  return "";
}

// Why `der` is not one X.509 certificate (version 1 or 3) in strict DER, or "": bytes after
// it, a form DER forbids (`der_problem`), a version 1 written out or a version 2 or 4.
std::string strict_der_certificate_problem(const std::string& der) {
  const auto* start = reinterpret_cast<const unsigned char*>(der.data());
  const unsigned char* p = start;
  std::unique_ptr<X509, decltype(&X509_free)> cert(
      d2i_X509(nullptr, &p, static_cast<long>(der.size())), &X509_free);
  ERR_clear_error();
  if (!cert) return "is not an X.509 certificate";
  if (p != start + der.size())
    return "is not an X.509 certificate (" + std::to_string(start + der.size() - p) +
           " bytes after it)";
  std::string problem = der_problem(start, start + der.size(), 32);
  if (problem.empty()) problem = certificate_parts_problem(start, start + der.size());
  if (!problem.empty()) return "is not in strict DER (" + problem + ")";
  if (X509_get_extension_flags(cert.get()) & EXFLAG_INVALID)
    return "is not an X.509 certificate (an extension given twice or unreadable)";
  for (int i = 0; i < X509_get_ext_count(cert.get()); ++i) {  // each one OpenSSL knows, read
    X509_EXTENSION* ext = X509_get_ext(cert.get(), i);
    const X509V3_EXT_METHOD* method = X509V3_EXT_get(ext);
    if (!method) continue;
    void* value = X509V3_EXT_d2i(ext);
    ERR_clear_error();
    if (!value) return "is not an X.509 certificate (an extension given twice or unreadable)";
    if (method->it)
      ASN1_item_free(static_cast<ASN1_VALUE*>(value), ASN1_ITEM_ptr(method->it));
    else if (method->ext_free)
      method->ext_free(value);
  }
  const long version = X509_get_version(cert.get());
  // the signed part's first element ([0], 0xA0, where a version is written out); the
  // lengths are in their shortest form here
  const size_t outer = 2 + (start[1] & 0x80 ? start[1] & 0x7F : 0);
  const size_t tbs = outer + 2 + (start[outer + 1] & 0x80 ? start[outer + 1] & 0x7F : 0);
  const bool written = tbs < der.size() && start[tbs] == 0xA0;
  if (version == 1 || version > 2 || (written && version != 2))
    return "is not an X.509 certificate (version " + std::to_string(version + 1) +
           (written && version == 0 ? " written out, which DER leaves out" : "") +
           "; versions 1 and 3 are read)";
  return "";
}

// Why a trusted certificate (strict DER, checked above) can anchor no chain in OpenSSL, or "":
// a key under kMinSecurityBits (RSA under 2048 bits); on a certificate not self-issued
// (issuer = subject), a signature under them (MD5, SHA-1), or not a CA (basicConstraints
// CA:TRUE and no key usage without keyCertSign; or, without basicConstraints, a key usage
// allowing keyCertSign). slamreloc.io.pem.trusted_certificates_problem's rule.
constexpr int kMinSecurityBits = 112;  // OpenSSL's level 2 (`MIN_SECURITY_BITS`)

std::string anchor_problem(const std::string& der) {
  const auto* p = reinterpret_cast<const unsigned char*>(der.data());
  std::unique_ptr<X509, decltype(&X509_free)> cert(
      d2i_X509(nullptr, &p, static_cast<long>(der.size())), &X509_free);
  ERR_clear_error();
  if (!cert) return "";
  char subject[256] = {0};
  X509_NAME_oneline(X509_get_subject_name(cert.get()), subject, sizeof subject - 1);
  const std::string which = std::string("(") + std::string(subject).substr(0, 80) + ")";
  EVP_PKEY* key = X509_get0_pubkey(cert.get());
  ERR_clear_error();
  const int bits = key ? EVP_PKEY_get_security_bits(key) : 0;
  if (key && bits > 0 && bits < kMinSecurityBits)
    return which + " has a key of " + std::to_string(bits) + " security bits, under the " +
           std::to_string(kMinSecurityBits) + " that OpenSSL clients hold a chain to (RSA: " +
           "2048 bits)";
  if (X509_NAME_cmp(X509_get_subject_name(cert.get()), X509_get_issuer_name(cert.get())) == 0)
    return "";
  int digest = 0, signature_bits = 0;
  if (!X509_get_signature_info(cert.get(), &digest, nullptr, &signature_bits, nullptr) ||
      signature_bits < kMinSecurityBits) {
    ERR_clear_error();
    const std::string name = digest == NID_md5 ? "MD5" : digest == NID_sha1 ? "SHA1"
                                                 : "a digest OpenSSL does not take";
    return which + " is signed with " + name + ", which OpenSSL clients refuse in a chain";
  }
  const uint32_t flags = X509_get_extension_flags(cert.get());
  const bool signs = !(flags & EXFLAG_KUSAGE) || (X509_get_key_usage(cert.get()) & KU_KEY_CERT_SIGN);
  const bool ca = (flags & EXFLAG_BCONS) ? (flags & EXFLAG_CA) && signs
                                         : (flags & EXFLAG_KUSAGE) && signs;
  if (ca) return "";
  return which + " is neither a CA nor self-signed, so no client can anchor a chain in it: "
                 "give the CA certificate that signed it";
}

// The trusted certificate(s) of --tls-ca, checked by the rule above (never by OpenSSL's PEM
// reader, which would prompt for a pass phrase on an encrypted-looking block).
std::string read_tls_ca(const fs::path& path) {
  std::string pem = read_file(path, "--tls-ca", kMaxPemBytes);
  const std::string name = path.string() + ": --tls-ca is not a PEM certificate";
  auto refuse = [&](const std::string& why) { throw Error(name + " (" + why + ")"); };
  if (pem.rfind("\xEF\xBB\xBF", 0) == 0)
    refuse("it starts with a UTF-8 byte-order mark, which gRPC's TLS does not read: save it "
           "without");
  std::optional<std::string> label;
  size_t opened = 0, number = 0, certificates = 0;
  std::vector<std::string> body, anchors;
  for (size_t pos = 0; pos <= pem.size();) {
    size_t nl = pem.find('\n', pos);
    if (nl == std::string::npos) nl = pem.size();
    std::string line = pem.substr(pos, nl - pos);
    pos = nl + 1;
    ++number;
    const std::string at = "line " + std::to_string(number);
    while (!line.empty() && line.back() == '\r') line.pop_back();
    const size_t width = line.size();  // BoringSSL reads a line 253 bytes at a time
    while (!line.empty() && (line.back() == ' ' || line.back() == '\t')) line.pop_back();
    for (unsigned char c : line)
      if ((c < 0x20 && c != '\t') || c == 0x7F) {
        char hex[8];
        std::snprintf(hex, sizeof hex, "0x%02x", c);
        refuse(at + " holds a control character (" + hex + ")");
      }
    const bool begin = starts_with(line, "-----BEGIN "), end = starts_with(line, "-----END ");
    if (!begin && !end &&
        (line.find("-----BEGIN ") != std::string::npos ||
         line.find("-----END ") != std::string::npos))
      refuse(at + " holds a PEM marker after other text");
    if (!label) {
      if (end) refuse(at + " ends a block that no BEGIN line opened");
      if (begin) {
        label = marker_label(line, "-----BEGIN ");
        if (!label) refuse(at + " is not a PEM marker line ('-----BEGIN LABEL-----')");
        if (*label == "TRUSTED CERTIFICATE")
          refuse(at + " opens a TRUSTED CERTIFICATE block, which TLS here does not read: write "
                      "it as a CERTIFICATE (openssl x509 -in FILE -out NEW)");
        opened = number;
        body.clear();
      }
      continue;
    }
    const std::string block = "block at line " + std::to_string(opened);
    if (begin) refuse(at + " opens a block inside the one opened at line " + std::to_string(opened));
    if (!end) {
      if (width > 76)
        refuse(at + " is " + std::to_string(width) + " characters long; a PEM line holds at "
                    "most 76 (rewrite the file with `openssl x509 -in FILE -out NEW`)");
      const size_t first = line.find_first_not_of(" \t");
      body.push_back(first == std::string::npos ? std::string() : line.substr(first));
      continue;
    }
    const std::optional<std::string> closing = marker_label(line, "-----END ");
    if (!closing) refuse(at + " is not a PEM marker line ('-----END LABEL-----')");
    if (*closing != *label)
      refuse(at + " ends '" + *closing + "', but line " + std::to_string(opened) + " opened '" +
             *label + "'");
    const bool certificate = *label == "CERTIFICATE" || *label == "X509 CERTIFICATE";
    const std::string what = "the " + (certificate ? std::string("certificate") : *label) + " " +
                             block;
    // base64 lines only: no "Name: value" headers (an encrypted block), no blank line
    if (std::any_of(body.begin(), body.end(),
                    [](const std::string& l) { return l.find(':') != std::string::npos; }))
      refuse(what + " has PEM headers (an encrypted or annotated block), which a certificate "
                    "file does not hold");
    std::string text;
    for (size_t i = 0; i < body.size(); ++i) {
      if (body[i].empty()) refuse(what + " has a blank line inside its base64");
      text += without_blanks(body[i]);
    }
    const std::optional<std::string> der = base64_bytes(text);
    if (!der) refuse(what + " is not base64");
    if (certificate) {
      const std::string why = strict_der_certificate_problem(*der);
      if (!why.empty()) refuse(what + " " + why);
      ++certificates;
      anchors.push_back(*der);
    }
    label.reset();
  }
  if (label) refuse("the block opened at line " + std::to_string(opened) + " has no END line");
  if (certificates == 0) refuse("no 'BEGIN CERTIFICATE' block");
  for (size_t i = 0; i < anchors.size(); ++i) {
    const std::string why = anchor_problem(anchors[i]);
    if (!why.empty())
      throw Error(path.string() + ": --tls-ca cannot be trusted: certificate " +
                  std::to_string(i + 1) + " " + why);
  }
  return pem;
}

// An image's name as the first field of an output line, by `slamreloc localize`'s rule
// (slamreloc.cli.jobs.line_name): as it is, or, where it holds a space, a '%', a character
// Python does not print (control, format, line break...) or bytes that are not UTF-8, or
// starts with '#', percent-encoded byte by byte (all but ASCII letters, digits and _.-~/),
// so that no name splits a line's fields, reads as a comment or writes a line of its own.
std::string line_name(const std::string& name) {
  bool encode = !name.empty() && name[0] == '#';
  for (std::size_t i = 0; i < name.size() && !encode;) {
    char32_t cp = 0;
    const int n = utf8_char(name, i, cp);
    encode = n == 0 || cp == '%' || cp == ' ' || !printable(cp);
    i += n == 0 ? 1 : n;
  }
  if (!encode) return name;
  static const char hex[] = "0123456789ABCDEF";
  std::string out;
  for (const unsigned char c : name) {
    const bool safe = (c >= 'A' && c <= 'Z') || (c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') ||
                      c == '_' || c == '.' || c == '-' || c == '~' || c == '/';
    if (safe) {
      out += static_cast<char>(c);
    } else {
      out += '%';
      out += hex[c >> 4];
      out += hex[c & 0xF];
    }
  }
  return out;
}

// `text` as one error line, by the CLI's rule (slamreloc.errors.terminal_line): each character
// Python does not print written as Python's ascii() writes it (\n, \x1b, \u200b), a byte that
// is not UTF-8 as the surrogate Python reads it as (\udcfe), and a run without spaces longer
// than kWordLimit characters cut in its middle, so that a file name can neither break the line
// nor drive a terminal, and a 2 MB name still leaves the problem at the line's end.
std::string terminal_line(const std::string& text) {
  constexpr std::size_t kWordLimit = 300;
  std::string line;
  for (std::size_t start = 0; start <= text.size();) {
    std::size_t stop = text.find(' ', start);
    if (stop == std::string::npos) stop = text.size();
    std::vector<std::string> word;  // the word as shown, one character per entry
    for (std::size_t i = start; i < stop;) {
      char32_t cp = 0;
      const int n = utf8_char(text, i, cp);
      char buf[16] = "";
      if (n == 0) {
        std::snprintf(buf, sizeof buf, "\\udc%02x", static_cast<unsigned char>(text[i]));
      } else if (cp == '\n' || cp == '\r' || cp == '\t') {
        std::snprintf(buf, sizeof buf, "\\%c", cp == '\n' ? 'n' : cp == '\r' ? 'r' : 't');
      } else if (!printable(cp)) {
        std::snprintf(buf, sizeof buf,
                      cp < 0x100 ? "\\x%02x" : cp < 0x10000 ? "\\u%04x" : "\\U%08x",
                      static_cast<unsigned>(cp));
      } else {
        word.push_back(text.substr(i, n));
      }
      for (const char* c = buf; *c != 0; ++c) word.emplace_back(1, *c);
      i += n == 0 ? 1 : n;
    }
    const std::size_t half = kWordLimit / 2;
    const bool cut = word.size() > kWordLimit;
    if (start > 0) line += ' ';
    for (std::size_t k = 0; k < word.size(); ++k) {
      if (cut && k == half) {
        line += "...(" + std::to_string(word.size()) + " characters)...";
        k = word.size() - half;
      }
      line += word[k];
    }
    start = stop + 1;
  }
  return line;
}

void print_result(const std::string& raw_name, const v1::LocalizeResponse& r) {
  const std::string name = line_name(raw_name);
  if (r.localized()) {
    const v1::Transform& t = r.world_from_cam();
    std::printf("%s %.17g %.17g %.17g %.17g %.17g %.17g %.17g %u\n", name.c_str(), t.tx(), t.ty(),
                t.tz(), t.qx(), t.qy(), t.qz(), t.qw(), r.num_inliers());
  } else {
    std::printf("# %s: not localized (%u inliers)\n", name.c_str(), r.num_inliers());
  }
  std::fflush(stdout);
}

// Errors of one image (the others are still sent): not decodable, or over a size limit.
bool is_image_error(const CallError& err) {
  return err.kind == "BAD_IMAGE" || err.kind == "TOO_LARGE" ||
         (err.kind.empty() && err.code == grpc::StatusCode::RESOURCE_EXHAUSTED);
}

int run(const Options& opts) {
  std::shared_ptr<grpc::ChannelCredentials> credentials = grpc::InsecureChannelCredentials();
  if (!opts.tls_ca.empty()) {  // the options' files first, then the sequence
    grpc::SslCredentialsOptions tls;
    tls.pem_root_certs = read_tls_ca(opts.tls_ca);
    credentials = grpc::SslCredentials(tls);
  }
  const std::vector<fs::path> images = sequence_images(opts.sequence);
  std::optional<v1::Camera> camera;
  if (!opts.camera.empty()) {
    camera.emplace();
    camera->set_colmap(opts.camera);
  }
  auto channel = grpc::CreateChannel(opts.server, credentials);
  auto stub = v1::Relocalizer::NewStub(channel);
  int status = 0;
  for (const fs::path& path : images) {
    std::string bytes;
    try {
      bytes = read_file(path, "image", kMaxImageBytes);
    } catch (const Error& err) {
      std::fprintf(stderr, "error: %s\n", terminal_line(err.what()).c_str());
      status = 2;
      continue;
    }
    try {
      print_result(path.filename().string(),
                   localize(*stub, bytes, camera ? &*camera : nullptr, opts.call));
    } catch (const CallError& err) {
      const std::string line = path.string() + ": server " + opts.server + ": " + err.what();
      std::fprintf(stderr, "error: %s\n", terminal_line(line).c_str());
      if (!is_image_error(err)) return 2;
      status = 2;
    }
  }
  return status;
}

}  // namespace

int main(int argc, char** argv) {
  // What fails reaches the user as one `error:` line with gRPC's status; gRPC's own log lines
  // (e.g. a failed TLS handshake) only where asked for with GRPC_VERBOSITY.
  if (std::getenv("GRPC_VERBOSITY") == nullptr) gpr_set_log_function([](gpr_log_func_args*) {});
  try {
    return run(parse_args(argc, argv));
  } catch (const std::exception& err) {
    std::fprintf(stderr, "error: %s\n", terminal_line(err.what()).c_str());
    return 2;
  }
}
