// The viewer's HTTP server: `ag2gs view MODEL_DIR`, and `ag2gs train ...
// --view`, which serves the same page while the model trains.
#pragma once

#include <chrono>
#include <condition_variable>
#include <functional>
#include <memory>
#include <mutex>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <utility>

#include "cli/viewer/view_session.h"
#include "host/io/model_io.h"

namespace httplib {
class Server;
}

namespace ag2gs::cli {

// What a training run shows through the viewer while it trains: snapshots
// of the model (taken by the training loop only while a page is asking for
// pictures, at most every kSnapshotMs), its progress and a pause switch.
// The training loop and the server's threads call it; each side's methods
// say which they are.
class LiveTraining {
 public:
  static constexpr int kSnapshotMs = 500;

  // `rt`: the server's own runtime; `options`: the scene and -r of the run.
  LiveTraining(Runtime& rt, ViewOptions options);

  // Training's side. True when a page asked for a picture since the last
  // snapshot and kSnapshotMs have passed since it.
  bool snapshot_wanted();
  // A new model to show; `final`: training has ended (selection works again).
  void publish(ModelArchive snapshot, bool final);
  // {"iteration", "iterations", "psnr", "gaussians", "eta_s", ...}.
  void set_status(const nlohmann::json& status);
  // Returns at once unless the page paused training; then when it resumes
  // it, or a signal arrives. (The pause counts in the run's training time.)
  void wait_while_paused();

  // The server's side (one request at a time).
  ViewSession& session();   // the newest snapshot's (built here on first use)
  nlohmann::json status();  // set_status's, with "paused" and "finished"
  void set_paused(bool paused);
  void asked_for_picture();

 private:
  Runtime& rt_;
  ViewOptions options_;
  std::mutex lock_;
  std::condition_variable changed_;
  std::optional<ModelArchive> pending_;
  bool pending_final_ = false;
  std::unique_ptr<ViewSession> session_;
  nlohmann::json status_ = nlohmann::json::object();
  bool paused_ = false, finished_ = false, asked_ = true;
  std::chrono::steady_clock::time_point last_snapshot_{};
};

struct ServeOptions {
  std::string host = "127.0.0.1";
  int port = 8080;
};

// Serves the page and its API. `session` is called with the server's lock
// held; `live` (may be null) adds GET/POST /api/train.
class ViewServer {
 public:
  ViewServer(std::function<ViewSession&()> session, LiveTraining* live, const ServeOptions& options);
  ~ViewServer();
  // Listens (a port in use is an error naming it) and prints "ag2gs view:
  // serving WHAT at http://HOST:PORT/"; returns the port.
  int bind(const std::string& what);
  // Answers requests until a signal arrives (InterruptGuard) or stop();
  // false when the server failed.
  bool run();
  void stop();

 private:
  void configure(const ServeOptions& options);
  void add_routes(std::function<ViewSession&()> session, LiveTraining* live);

  std::unique_ptr<httplib::Server> svr_;
  ServeOptions options_;
  std::mutex lock_;  // one request at a time touches the session
};

}  // namespace ag2gs::cli
