// A robot loop over the gRPC Control stream in C++: one session, one act at a time, as a controller would run it.
//
//   control_loop TARGET SESSION_ID --obs V1,V2,... [--acts N | --seconds S] [--token T] [--print-actions]
//
// Sends the same observation every step (a latency probe, or a starting point for a real controller that reads
// its sensors instead) and prints one JSON object: the acts answered, the round trip's p50 and p99 in ms (the
// first tenth dropped as warm-up), the in-band errors and the first error's message, and with --print-actions the
// actions answered. Exit status: 0 when every act was answered with an action, 1 when one was answered with an
// error or the stream failed, 2 on bad arguments. Built by clients/cpp/build.sh (`make cpp-client`).
#include <grpcpp/grpcpp.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <sstream>
#include <string>
#include <vector>

#include "gmt/v1/policy.grpc.pb.h"

namespace {

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
      std::stringstream in(argv[++i]);
      std::string v;
      while (std::getline(in, v, ',')) {
        char* end = nullptr;
        const float x = std::strtof(v.c_str(), &end);
        if (v.empty() || *end != '\0') return usage(("--obs: not a number: " + v).c_str());
        obs.push_back(x);
      }
    } else if (a == "--acts" && has_value) {
      acts = std::atol(argv[++i]);
      if (acts <= 0) return usage("--acts must be a positive integer");
    } else if (a == "--seconds" && has_value) {
      seconds = std::atof(argv[++i]);
      if (seconds <= 0) return usage("--seconds must be positive");
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
  grpc::ClientContext ctx;
  ctx.AddMetadata("x-session-id", sid);  // the key a proxy routes the session's calls by
  if (!token.empty()) ctx.AddMetadata("authorization", "Bearer " + token);
  auto stream = stub->Control(&ctx);

  gmt::v1::ControlRequest req;
  gmt::v1::ActRequest* act = req.mutable_act();
  act->set_session_id(sid);
  for (float x : obs) act->mutable_values()->add_values(x);

  using clock = std::chrono::steady_clock;
  const auto stop = clock::now() + std::chrono::duration_cast<clock::duration>(std::chrono::duration<double>(
                                       seconds > 0 ? seconds : 0.0));
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
  stream->WritesDone();
  const grpc::Status status = stream->Finish();

  std::vector<double> kept(ms.begin() + ms.size() / 10, ms.end());
  std::sort(kept.begin(), kept.end());
  auto pct = [&](double p) {
    return kept.empty() ? 0.0 : kept[std::min(kept.size() - 1, static_cast<size_t>(p * kept.size()))];
  };
  std::printf("{\"acts\": %zu, \"p50_ms\": %.3f, \"p99_ms\": %.3f, \"errors\": %ld, \"first_error\": %s, "
              "\"status\": %s",
              ms.size(), pct(0.50), pct(0.99), errors, json_string(first_error).c_str(),
              json_string(status.ok() ? "OK" : std::to_string(status.error_code()) + ": " + status.error_message())
                  .c_str());
  if (print_actions) {
    std::printf(", \"actions\": [");
    for (size_t i = 0; i < actions.size(); ++i) {
      std::printf(i ? ", [" : "[");
      for (size_t j = 0; j < actions[i].size(); ++j) std::printf(j ? ", %.9g" : "%.9g", actions[i][j]);
      std::printf("]");
    }
    std::printf("]");
  }
  std::printf("}\n");
  return broken || errors || !status.ok() ? 1 : 0;
}
