// A robot loop over the gRPC Control stream in C++: one session, one act at a time, as a controller would run it.
//
//   control_loop TARGET SESSION_ID --obs V1,V2,... [--acts N | --seconds S] [--token T] [--print-actions]
//
// Sends the same observation every step (a latency probe, or a starting point for a real controller that reads
// its sensors instead) and prints one JSON object: the acts answered, the seconds they took, the round trip's p50
// and p99 in ms (the first tenth dropped as warm-up; linear interpolation, as numpy's percentile; null when no act
// was answered), the in-band errors and the first error's `code: message`, the stream's final status, and with
// --print-actions the actions answered. Exit status: 0 when at least one act was answered and every act was
// answered with an action, 1 otherwise (an in-band error, a broken stream, no act), 2 on bad arguments. With
// --seconds the stream's deadline is that long plus 10 s, so a server that stops answering ends the run.
// Built by clients/cpp/build.sh (`make cpp-client`).
#include <grpcpp/grpcpp.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <sstream>
#include <string>
#include <vector>

#include "gmt/v1/policy.grpc.pb.h"

namespace {

// gRPC's status codes by number, as the other clients name them.
const std::string kStatusNames[] = {"OK", "CANCELLED", "UNKNOWN", "INVALID_ARGUMENT", "DEADLINE_EXCEEDED",
                                    "NOT_FOUND", "ALREADY_EXISTS", "PERMISSION_DENIED", "RESOURCE_EXHAUSTED",
                                    "FAILED_PRECONDITION", "ABORTED", "OUT_OF_RANGE", "UNIMPLEMENTED", "INTERNAL",
                                    "UNAVAILABLE", "DATA_LOSS", "UNAUTHENTICATED"};

int usage(const char* why) {
  std::fprintf(stderr,
               "control_loop: %s\nusage: control_loop TARGET SESSION_ID --obs V1,V2,... [--acts N | --seconds S] "
               "[--token T] [--print-actions]\n",
               why);
  return 2;
}

// A JSON string literal of `s` (quotes, backslashes and control characters escaped).
std::string json_string(const std::string& s) {
  std::string out = "\"";
  for (unsigned char c : s) {
    if (c == '"' || c == '\\') {
      out += '\\';
      out += static_cast<char>(c);
    } else if (c < 0x20) {
      char buf[8];
      std::snprintf(buf, sizeof buf, "\\u%04x", c);
      out += buf;
    } else {
      out += static_cast<char>(c);
    }
  }
  return out + "\"";
}

// `s` as a whole number in [lo, hi] (false when it is not one, or out of range).
bool parse_long(const char* s, long lo, long hi, long* out) {
  char* end = nullptr;
  errno = 0;
  const long v = std::strtol(s, &end, 10);
  if (end == s || *end != '\0' || errno == ERANGE || v < lo || v > hi) return false;
  *out = v;
  return true;
}

// `s` as a finite number in (lo, hi] (false when it is not one, or out of range).
bool parse_double(const char* s, double lo, double hi, double* out) {
  char* end = nullptr;
  errno = 0;
  const double v = std::strtod(s, &end);
  if (end == s || *end != '\0' || errno == ERANGE || !std::isfinite(v) || v <= lo || v > hi) return false;
  *out = v;
  return true;
}

// The p-th percentile (0..1) of sorted `v`, interpolated linearly between neighbours (numpy's default).
double percentile(const std::vector<double>& v, double p) {
  const double at = p * (v.size() - 1);
  const size_t i = static_cast<size_t>(at);
  return i + 1 < v.size() ? v[i] + (at - i) * (v[i + 1] - v[i]) : v[i];
}

}  // namespace

int main(int argc, char** argv) {
  if (argc < 3) return usage("TARGET and SESSION_ID are required");
  const std::string target = argv[1], sid = argv[2];
  std::vector<float> obs;
  long acts = -1;
  double seconds = -1;
  std::string token;
  bool print_actions = false;
  for (int i = 3; i < argc; ++i) {
    const std::string a = argv[i];
    const bool has_value = i + 1 < argc;
    if (a == "--obs" && has_value) {
      const std::string list = argv[++i];
      if (list.empty() || list.back() == ',') return usage("--obs: a comma-separated list of numbers");
      obs.clear();
      std::stringstream in(list);
      std::string v;
      while (std::getline(in, v, ',')) {
        char* end = nullptr;
        const float x = std::strtof(v.c_str(), &end);
        if (v.empty() || *end != '\0') return usage(("--obs: not a number: '" + v + "'").c_str());
        obs.push_back(x);  // the server refuses NaN, infinities and out-of-range values itself
      }
    } else if (a == "--acts" && has_value) {
      if (!parse_long(argv[++i], 1, 1000000000L, &acts)) return usage("--acts must be a whole number in 1..1e9");
    } else if (a == "--seconds" && has_value) {
      if (!parse_double(argv[++i], 0.0, 1e6, &seconds)) return usage("--seconds must be a number in (0, 1e6]");
    } else if (a == "--token" && has_value) {
      token = argv[++i];
    } else if (a == "--print-actions") {
      print_actions = true;
    } else {
      return usage(("unknown or incomplete option " + a).c_str());
    }
  }
  if (obs.empty()) return usage("--obs is required");
  if ((acts > 0) == (seconds > 0)) return usage("give one of --acts and --seconds");

  auto stub = gmt::v1::PolicyService::NewStub(grpc::CreateChannel(target, grpc::InsecureChannelCredentials()));
  using clock = std::chrono::steady_clock;
  const auto start = clock::now();
  const auto stop = start + std::chrono::duration_cast<clock::duration>(std::chrono::duration<double>(
                                std::max(seconds, 0.0)));
  grpc::ClientContext ctx;
  ctx.AddMetadata("x-session-id", sid);  // the key a proxy routes the session's calls by
  if (!token.empty()) ctx.AddMetadata("authorization", "Bearer " + token);
  if (seconds > 0) {  // a server that stops answering ends the run (DEADLINE_EXCEEDED) instead of hanging it
    ctx.set_deadline(std::chrono::system_clock::now() + std::chrono::duration_cast<std::chrono::system_clock::duration>(
                                                            std::chrono::duration<double>(seconds + 10.0)));
  }
  auto stream = stub->Control(&ctx);

  gmt::v1::ControlRequest req;
  gmt::v1::ActRequest* act = req.mutable_act();
  act->set_session_id(sid);
  for (float x : obs) act->mutable_values()->add_values(x);

  gmt::v1::ControlResponse answer;
  std::vector<double> ms;
  std::vector<std::vector<float>> actions;
  long errors = 0;
  std::string first_error;
  bool broken = false;
  while (acts > 0 ? static_cast<long>(ms.size()) < acts : clock::now() < stop) {
    const auto t = clock::now();
    if (!stream->Write(req) || !stream->Read(&answer)) {
      broken = true;
      break;
    }
    ms.push_back(std::chrono::duration<double, std::milli>(clock::now() - t).count());
    if (answer.result_case() == gmt::v1::ControlResponse::kAct) {
      if (print_actions) actions.emplace_back(answer.act().action().begin(), answer.act().action().end());
    } else {
      ++errors;
      if (first_error.empty())
        first_error = answer.has_error() ? answer.error().code() + ": " + answer.error().message() : "no act answer";
    }
  }
  const double took = std::chrono::duration<double>(clock::now() - start).count();
  if (!broken) stream->WritesDone();
  const grpc::Status status = stream->Finish();

  std::vector<double> kept(ms.begin() + ms.size() / 10, ms.end());
  std::sort(kept.begin(), kept.end());
  std::string p50 = "null", p99 = "null";
  if (!kept.empty()) {
    char buf[32];
    std::snprintf(buf, sizeof buf, "%.3f", percentile(kept, 0.50));
    p50 = buf;
    std::snprintf(buf, sizeof buf, "%.3f", percentile(kept, 0.99));
    p99 = buf;
  }
  std::printf("{\"acts\": %zu, \"seconds\": %.3f, \"p50_ms\": %s, \"p99_ms\": %s, \"errors\": %ld, "
              "\"first_error\": %s, \"stream_broken\": %s, \"status\": %s",
              ms.size(), took, p50.c_str(), p99.c_str(), errors, json_string(first_error).c_str(),
              broken ? "true" : "false",
              json_string(status.ok() ? "OK" : kStatusNames[std::min(int(status.error_code()), 16)] + ": " +
                                                   status.error_message())
                  .c_str());
  if (print_actions) {
    std::printf(", \"actions\": [");
    for (size_t i = 0; i < actions.size(); ++i) {
      std::printf(i ? ", [" : "[");
      for (size_t j = 0; j < actions[i].size(); ++j) {
        const float x = actions[i][j];
        if (std::isfinite(x))
          std::printf(j ? ", %.9g" : "%.9g", x);
        else
          std::printf(j ? ", null" : "null");  // JSON has no NaN or infinity
      }
      std::printf("]");
    }
    std::printf("]");
  }
  std::printf("}\n");
  std::fflush(stdout);
  return ms.empty() || broken || errors || !status.ok() ? 1 : 0;
}
