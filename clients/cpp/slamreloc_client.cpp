// slamreloc_client: localize the images of a sequence with a `slamreloc serve` server.
//
//   slamreloc_client --server HOST:PORT [--map NAME] [--token T] [--tls-ca PEM]
//                    [--camera "MODEL W H ..."] [--timeout SECONDS] SEQUENCE
//
// --token (default: $SLAMRELOC_TOKEN) is sent as `authorization: Bearer T`; --tls-ca: connect
// with TLS, trusting the certificate(s) in that PEM file (else plain TCP).
//
// SEQUENCE is a 7-Scenes sequence folder (frame-XXXXXX.color.png or .color.jpg, in name order)
// or a TUM RGB-D folder (rgb.txt: `timestamp rgb/file.png` lines, in the order listed). Each
// image's file is sent as it is (the server decodes it) and one line is printed per image, as
// `slamreloc localize` prints it (with all the digits of a double):
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
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <iterator>
#include <memory>
#include <optional>
#include <sstream>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include <grpc/support/log.h>
#include <grpcpp/grpcpp.h>

#include "relocalizer.grpc.pb.h"

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
  if (const char* token = std::getenv("SLAMRELOC_TOKEN")) opts.call.token = token;
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
      opts.server = value;
    } else if (arg == "--map") {
      opts.call.map = value;
    } else if (arg == "--token") {
      opts.call.token = value;
    } else if (arg == "--tls-ca") {
      opts.tls_ca = value;
    } else if (arg == "--camera") {
      opts.camera = value;
    } else if (arg == "--timeout") {
      char* end = nullptr;
      const double seconds = std::strtod(value.c_str(), &end);
      if (value.empty() || *end != '\0' || !(seconds > 0 && seconds < 1e6))
        throw Error("--timeout: " + value + " is not a positive number of seconds");
      opts.call.timeout = std::chrono::milliseconds(static_cast<long long>(seconds * 1000));
    } else {
      throw Error(arg + ": unknown option (see --help)");
    }
  }
  if (opts.server.empty()) throw Error("--server HOST:PORT is required (see --help)");
  if (positional.size() != 1) throw Error("give one SEQUENCE folder (see --help)");
  opts.sequence = positional[0];
  return opts;
}

// The images of a 7-Scenes sequence folder (name order) or a TUM RGB-D folder (rgb.txt order).
std::vector<fs::path> sequence_images(const fs::path& dir) {
  std::error_code ec;
  if (!fs::is_directory(dir, ec))
    throw Error(dir.string() + (fs::exists(dir, ec) ? ": not a folder" : ": no such folder"));
  std::vector<fs::path> images;
  const fs::path list = dir / "rgb.txt";
  if (fs::is_regular_file(list, ec)) {
    std::ifstream in(list);
    if (!in) throw Error(list.string() + ": cannot be read");
    std::string line;
    for (int n = 1; std::getline(in, line); ++n) {
      std::istringstream fields(line);
      std::string stamp, file, extra;
      if (!(fields >> stamp) || stamp[0] == '#') continue;  // blank line or comment
      if (!(fields >> file) || (fields >> extra))
        throw Error(list.string() + ":" + std::to_string(n) + ": expected `timestamp file`");
      images.push_back(dir / file);
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

std::string read_file(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw Error(path.string() + ": cannot be opened");
  std::string bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
  if (in.bad()) throw Error(path.string() + ": cannot be read");
  return bytes;
}

void print_result(const std::string& name, const v1::LocalizeResponse& r) {
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
  const std::vector<fs::path> images = sequence_images(opts.sequence);
  std::optional<v1::Camera> camera;
  if (!opts.camera.empty()) {
    camera.emplace();
    camera->set_colmap(opts.camera);
  }
  std::shared_ptr<grpc::ChannelCredentials> credentials = grpc::InsecureChannelCredentials();
  if (!opts.tls_ca.empty()) {
    grpc::SslCredentialsOptions tls;
    tls.pem_root_certs = read_file(opts.tls_ca);
    credentials = grpc::SslCredentials(tls);
  }
  auto channel = grpc::CreateChannel(opts.server, credentials);
  auto stub = v1::Relocalizer::NewStub(channel);
  int status = 0;
  for (const fs::path& path : images) {
    std::string bytes;
    try {
      bytes = read_file(path);
    } catch (const Error& err) {
      std::fprintf(stderr, "error: %s\n", err.what());
      status = 2;
      continue;
    }
    try {
      print_result(path.filename().string(),
                   localize(*stub, bytes, camera ? &*camera : nullptr, opts.call));
    } catch (const CallError& err) {
      std::fprintf(stderr, "error: %s: server %s: %s\n", path.string().c_str(),
                   opts.server.c_str(), err.what());
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
    std::fprintf(stderr, "error: %s\n", err.what());
    return 2;
  }
}
