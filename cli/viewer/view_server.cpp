// view: a local web page to look around a trained model, click an object,
// type a query and see the selection. An HTTP server (cpp-httplib) in front
// of a ViewSession; the page (cli/viewer/page.html) is compiled into the
// program, so it works offline. The API is documented in docs/formats.md.
#include "cli/viewer/view_server.h"

#include <spdlog/spdlog.h>
#include <sys/socket.h>

#include <algorithm>
#include <atomic>
#include <cctype>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <map>
#include <mutex>
#include <sstream>
#include <thread>

#include "cli/commands.h"
#include "cli/run_guard.h"
#include "cli/viewer/view_session.h"
#include "host/io/json_input.h"

// Last: httplib.h pulls in <resolv.h>, whose `_res` macro breaks Eigen's
// headers (a parameter of that name) when they come after it.
#include <httplib.h>

namespace ag2gs::cli {

const std::string& viewer_page();  // generated from cli/viewer/page.html

namespace {

// Request bodies are small JSON objects; anything larger is refused (413).
constexpr size_t kMaxBody = 64 * 1024;

struct ViewArgs {
  ViewOptions options;
  ServeOptions serve;
};

void send_json(httplib::Response& res, const nlohmann::json& j, int status = 200) {
  res.status = status;
  // Messages may quote what a request sent, which need not be UTF-8.
  res.set_content(j.dump(-1, ' ', false, nlohmann::json::error_handler_t::replace), "application/json");
}

void send_error(httplib::Response& res, int status, const std::string& message) {
  send_json(res, {{"error", message}}, status);
}

// s as a finite number, all of it (no trailing characters).
bool parse_finite(const std::string& s, double* v) {
  size_t used = 0;
  try {
    *v = std::stod(s, &used);
  } catch (const std::exception&) {
    return false;
  }
  return used > 0 && used == s.size() && std::isfinite(*v);
}

// A finite number from a query parameter.
double number_param(const httplib::Request& req, const char* name) {
  if (!req.has_param(name)) throw std::invalid_argument(std::string("missing parameter ") + name);
  const std::string s = req.get_param_value(name);
  double v = 0;
  if (!parse_finite(s, &v)) throw std::invalid_argument(std::string(name) + "='" + s + "' is not a finite number");
  return v;
}

int int_param(const httplib::Request& req, const char* name, int fallback) {
  if (!req.has_param(name)) return fallback;
  const double v = number_param(req, name);
  if (v != std::floor(v) || std::fabs(v) > 1e9) throw std::invalid_argument(std::string(name) + " must be a whole number");
  return static_cast<int>(v);
}

std::vector<double> number_list(const std::string& s, const char* name) {
  std::vector<double> out;
  std::stringstream ss(s);
  std::string item;
  while (std::getline(ss, item, ',')) {
    double v = 0;
    if (!parse_finite(item, &v)) throw std::invalid_argument(std::string(name) + ": '" + item + "' is not a finite number");
    out.push_back(v);
  }
  return out;
}

// The camera a render or click names: ?view=NAME, or ?pose=...&fx=..&w=..
Camera camera_of(const ViewSession& session, const httplib::Request& req) {
  if (req.has_param("view")) {
    // A training view, at its size or at w x h (the intrinsics scaled).
    const Camera c = session.view_camera(req.get_param_value("view"));
    if (!req.has_param("w") && !req.has_param("h")) return c;
    return ViewSession::resized(c, int_param(req, "w", 0), int_param(req, "h", 0));
  }
  if (!req.has_param("pose")) throw std::invalid_argument("give view=NAME or pose=R11,...,R33,t1,t2,t3 with fx, fy, cx, cy, w, h");
  return ViewSession::pose_camera(number_list(req.get_param_value("pose"), "pose"), number_param(req, "fx"),
                                  number_param(req, "fy"), number_param(req, "cx"), number_param(req, "cy"),
                                  int_param(req, "w", 0), int_param(req, "h", 0));
}

double json_number(const nlohmann::json& j, const char* key) {
  if (!j.contains(key) || !j[key].is_number())
    throw std::invalid_argument(std::string("\"") + key + "\" must be a number");
  const double v = j[key].get<double>();
  if (!std::isfinite(v)) throw std::invalid_argument(std::string("\"") + key + "\" must be finite");
  return v;
}

std::string json_string(const nlohmann::json& j, const char* key) {
  if (!j.contains(key) || !j[key].is_string()) throw std::invalid_argument(std::string("\"") + key + "\" must be a string");
  return j[key].get<std::string>();
}

constexpr size_t kWorkers = 32;
// Render clients remembered for superseding (the ids of open pages).
constexpr size_t kMaxClients = 4096;

// The Host values served: the loopback names and the address given with
// --host, each with or without a port. Empty: any (a viewer opened to the
// network with 0.0.0.0 or :: cannot know the names it is reached by).
std::vector<std::string> allowed_hosts(const std::string& host) {
  if (host == "0.0.0.0" || host == "::") return {};
  std::vector<std::string> names = {"127.0.0.1", "localhost", "[::1]"};
  names.push_back(host.find(':') != std::string::npos ? "[" + host + "]" : host);
  return names;
}

bool host_allowed(const std::string& value, const std::vector<std::string>& names) {
  if (names.empty() || value.empty()) return true;  // no Host header: not a browser
  std::string name = value;
  const size_t colon = name.rfind(':');
  if (colon != std::string::npos && name.find(']', colon) == std::string::npos &&
      (name[0] == '[' || name.find(':') == colon))
    name = name.substr(0, colon);  // the port
  std::transform(name.begin(), name.end(), name.begin(), [](unsigned char c) { return std::tolower(c); });
  return std::find(names.begin(), names.end(), name) != names.end();
}

struct Refusal {
  int status = 0;  // 0: served
  std::string message;
};

// Before routing: a page on another site that a browser opens cannot reach
// the viewer through a name that resolves to this machine (DNS rebinding:
// the Host header is that name), nor change its state with a form or a
// text/plain request (a JSON content type needs a CORS preflight, which
// the viewer does not grant); a POST without a Content-Length is answered
// at once instead of waiting for a body until the read timeout.
Refusal refusal(const httplib::Request& req, const std::vector<std::string>& hosts) {
  if (!host_allowed(req.get_header_value("Host"), hosts))
    return {403, "Host '" + req.get_header_value("Host") +
                     "' is not this viewer's address (open it as http://127.0.0.1:PORT/ or the --host given)"};
  if (req.method != "POST") return {};
  if (!req.has_header("Content-Length") && !req.has_header("Transfer-Encoding"))
    return {411, "a POST needs a Content-Length (and a JSON body, {} for none)"};
  const std::string type = req.get_header_value("Content-Type");
  if (type.rfind("application/json", 0) != 0)
    return {415, "a POST's body must be JSON, sent with Content-Type: application/json (got '" + type + "')"};
  return {};
}

nlohmann::json parse_body(const httplib::Request& req) {
  nlohmann::json j;
  try {
    j = req.body.empty() ? nlohmann::json::object() : parse_json_input(req.body, "the request body");
  } catch (const std::runtime_error& e) {
    throw std::invalid_argument(std::string("the request body is not JSON (or nests past ") +
                                std::to_string(kJsonMaxDepth) + " levels): " + e.what());
  }
  if (!j.is_object()) throw std::invalid_argument("the request body must be a JSON object");
  return j;
}

nlohmann::json run_query_request(ViewSession& session, const nlohmann::json& j) {
  if (j.contains("text")) return session.text(json_string(j, "text"));
  if (j.contains("view")) return session.click_view(json_string(j, "view"), json_number(j, "x"), json_number(j, "y"));
  if (j.contains("pose")) {
    if (!j["pose"].is_array()) throw std::invalid_argument("\"pose\" must be an array of 12 numbers");
    std::vector<double> pose;
    for (const auto& v : j["pose"]) {
      if (!v.is_number()) throw std::invalid_argument("\"pose\" must be an array of 12 numbers");
      pose.push_back(v.get<double>());
    }
    const double w = json_number(j, "w"), h = json_number(j, "h");
    const Camera cam = ViewSession::pose_camera(pose, json_number(j, "fx"), json_number(j, "fy"), json_number(j, "cx"),
                                                json_number(j, "cy"), static_cast<int>(std::clamp(w, -1.0, 1e6)),
                                                static_cast<int>(std::clamp(h, -1.0, 1e6)));
    return session.click_camera(cam, json_number(j, "x"), json_number(j, "y"));
  }
  throw std::invalid_argument(
      "give {\"view\": NAME, \"x\": X, \"y\": Y} (a click in a training view's full-size pixels), {\"pose\": [...], "
      "\"fx\", \"fy\", \"cx\", \"cy\", \"w\", \"h\", \"x\", \"y\"} (a click in a posed camera) or {\"text\": PHRASE}");
}

}  // namespace

LiveTraining::LiveTraining(Runtime& rt, ViewOptions options) : rt_(rt), options_(std::move(options)) {
  options_.training = true;
}

bool LiveTraining::snapshot_wanted() {
  std::lock_guard<std::mutex> g(lock_);
  if (!asked_) return false;
  const auto now = std::chrono::steady_clock::now();
  if (now - last_snapshot_ < std::chrono::milliseconds(kSnapshotMs)) return false;
  return true;
}

void LiveTraining::publish(ModelArchive snapshot, bool final) {
  std::lock_guard<std::mutex> g(lock_);
  pending_ = std::move(snapshot);
  pending_final_ = final;
  if (final) finished_ = true;
  asked_ = false;
  last_snapshot_ = std::chrono::steady_clock::now();
}

void LiveTraining::set_status(const nlohmann::json& status) {
  std::lock_guard<std::mutex> g(lock_);
  status_ = status;
}

void LiveTraining::wait_while_paused() {
  std::unique_lock<std::mutex> g(lock_);
  if (!paused_) return;
  spdlog::info("paused from the viewer; resume there (or Ctrl-C to stop with a checkpoint)");
  while (paused_ && !InterruptGuard::interrupted()) changed_.wait_for(g, std::chrono::milliseconds(50));
}

ViewSession& LiveTraining::session() {
  std::optional<ModelArchive> next;
  bool final = false;
  {
    std::lock_guard<std::mutex> g(lock_);
    next.swap(pending_);
    final = pending_final_;
  }
  if (next) {
    ViewOptions o = options_;
    o.training = !final;
    // The server's lock is held: no request uses the old session any more.
    session_ = std::make_unique<ViewSession>(
        rt_, o,
        trained_model_from_archive(
            std::move(*next),
            final ? (std::filesystem::path(o.model) / "model.ag2gs").string() : "the model in training", false));
  }
  if (!session_) throw std::runtime_error("the first picture of the model comes after its first iteration");
  return *session_;
}

nlohmann::json LiveTraining::status() {
  std::lock_guard<std::mutex> g(lock_);
  nlohmann::json j = status_;
  j["paused"] = paused_;
  j["finished"] = finished_;
  return j;
}

void LiveTraining::set_paused(bool paused) {
  {
    std::lock_guard<std::mutex> g(lock_);
    if (finished_ && paused) throw std::invalid_argument("training has ended; there is nothing to pause");
    paused_ = paused;
  }
  changed_.notify_all();
}

void LiveTraining::asked_for_picture() {
  std::lock_guard<std::mutex> g(lock_);
  asked_ = true;
}

ViewServer::ViewServer(std::function<ViewSession&()> session, LiveTraining* live, const ServeOptions& options)
    : svr_(std::make_unique<httplib::Server>()), options_(options) {
  if (options.port < 0 || options.port > 65535) throw std::invalid_argument("--port: from 0 (any free port) to 65535");
  configure(options);
  add_routes(std::move(session), live);
}

// Limits, sockets, the host check and the error answers.
void ViewServer::configure(const ServeOptions& options) {
  httplib::Server& svr = *svr_;
  svr.set_payload_max_length(kMaxBody);
  svr.set_read_timeout(10, 0);
  // Answers go out at once: without TCP_NODELAY a kept-alive connection
  // waits ~40 ms for the client's delayed ACK on every response.
  svr.set_tcp_nodelay(true);
  // SO_REUSEADDR only: cpp-httplib's default also sets SO_REUSEPORT, with
  // which a second viewer on the same port silently shares the requests.
  svr.set_socket_options([](socket_t sock) {
    int yes = 1;
    setsockopt(sock, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof yes);
  });
  // Idle kept-alive connections hold a worker each: enough workers that a
  // browser's connections (6 per page) from a few tabs never queue a
  // request, and idle ones closed after 2 s.
  svr.new_task_queue = [] { return new httplib::ThreadPool(kWorkers); };
  svr.set_keep_alive_timeout(2);
  svr.set_keep_alive_max_count(10000);
  const std::vector<std::string> hosts = allowed_hosts(options.host);
  svr.set_pre_routing_handler([hosts](const httplib::Request& req, httplib::Response& res) {
    const Refusal r = refusal(req, hosts);
    if (r.status == 0) return httplib::Server::HandlerResponse::Unhandled;
    send_error(res, r.status, r.message);
    return httplib::Server::HandlerResponse::Handled;
  });
  svr.set_exception_handler([](const httplib::Request&, httplib::Response& res, std::exception_ptr ep) {
    try {
      std::rethrow_exception(ep);
    } catch (const std::invalid_argument& e) {
      send_error(res, 400, e.what());
    } catch (const std::exception& e) {
      spdlog::error("request failed: {}", e.what());
      send_error(res, 500, e.what());
    } catch (...) {
      send_error(res, 500, "unknown error");
    }
  });
  svr.set_error_handler(httplib::Server::HandlerWithResponse(
      [](const httplib::Request& req, httplib::Response& res) -> httplib::Server::HandlerResponse {
    if (!res.body.empty()) return httplib::Server::HandlerResponse::Unhandled;
    send_error(res, res.status,
               res.status == 404 ? "no such endpoint: " + req.method + " " + req.path
               : res.status == 413 ? "request body over " + std::to_string(kMaxBody) + " bytes"
                                   : "HTTP " + std::to_string(res.status));
    return httplib::Server::HandlerResponse::Handled;
  }));
}

// The page and the API.
void ViewServer::add_routes(std::function<ViewSession&()> session, LiveTraining* live) {
  // Renders that carry `client=ID` (the page sends one per page load): a
  // request still waiting for the lock when a newer one of its client
  // arrives is answered 204 without rendering (X-Superseded: 1), so a
  // client that asks faster than the device renders gets its latest
  // camera next, not a backlog of old ones.
  struct Clients {
    std::mutex lock;
    std::map<std::string, uint64_t> latest;  // client -> arrival number of its newest render
    uint64_t arrivals = 0;
  };
  auto clients = std::make_shared<Clients>();
  httplib::Server& svr = *svr_;
  svr.Get("/", [](const httplib::Request&, httplib::Response& res) {
    res.set_header("Cache-Control", "no-store");
    res.set_content(viewer_page(), "text/html; charset=utf-8");
  });
  svr.Get("/api/info", [this, session, live, clients](const httplib::Request&, httplib::Response& res) {
    std::lock_guard<std::mutex> g(lock_);
    send_json(res, session().info());
  });
  svr.Get("/api/render", [this, session, live, clients](const httplib::Request& req, httplib::Response& res) {
    const ViewMode mode = parse_view_mode(req.has_param("mode") ? req.get_param_value("mode") : "rgb");
    const int quality = int_param(req, "quality", 85);
    std::string client;
    uint64_t arrival = 0;
    if (req.has_param("client")) {
      client = req.get_param_value("client");
      if (client.empty() || client.size() > 64)
        throw std::invalid_argument("client: an id of 1 to 64 characters (the page makes one per page load)");
      std::lock_guard<std::mutex> l(clients->lock);
      if (clients->latest.size() >= kMaxClients)
        clients->latest.clear();  // ids of closed pages; at worst one stale frame renders
      arrival = ++clients->arrivals;
      clients->latest[client] = arrival;
    }
    std::lock_guard<std::mutex> g(lock_);
    if (!client.empty()) {
      std::lock_guard<std::mutex> l(clients->lock);
      const auto it = clients->latest.find(client);
      if (it != clients->latest.end() && it->second != arrival) {
        res.status = 204;
        res.set_header("X-Superseded", "1");
        res.set_header("Cache-Control", "no-store");
        return;
      }
    }
    const std::string format = req.has_param("format") ? req.get_param_value("format") : "jpeg";
    if (format != "jpeg" && format != "png")
      throw std::invalid_argument("format '" + format + "': choose jpeg (the default) or png (a screenshot)");
    if (live) live->asked_for_picture();
    const Camera cam = camera_of(session(), req);
    double ms = 0;
    const std::vector<uint8_t> image = session().render_image(cam, mode, quality, format == "png", &ms);
    res.set_header("X-Render-Ms", std::to_string(ms));
    res.set_header("Cache-Control", "no-store");
    res.set_content(reinterpret_cast<const char*>(image.data()), image.size(),
                    format == "png" ? "image/png" : "image/jpeg");
  });
  svr.Post("/api/query", [this, session, live, clients](const httplib::Request& req, httplib::Response& res) {
    const nlohmann::json body = parse_body(req);
    std::lock_guard<std::mutex> g(lock_);
    const nlohmann::json r = run_query_request(session(), body);
    spdlog::info("query {}: {} anchors, {} Gaussians in {:.1f} ms", r["query"].dump(), r["anchors"].get<size_t>(),
                 r["gaussians"].get<size_t>(), r["ms"].get<double>());
    send_json(res, r);
  });
  svr.Get("/api/mask", [this, session, live, clients](const httplib::Request& req, httplib::Response& res) {
    std::lock_guard<std::mutex> g(lock_);
    const std::vector<uint8_t> png = session().mask_png(camera_of(session(), req));
    res.set_header("Cache-Control", "no-store");
    res.set_content(reinterpret_cast<const char*>(png.data()), png.size(), "image/png");
  });
  svr.Get("/api/selection.ply", [this, session, live, clients](const httplib::Request&, httplib::Response& res) {
    std::lock_guard<std::mutex> g(lock_);
    const std::vector<uint8_t> ply = session().selection_ply();
    res.set_header("Content-Disposition", "attachment; filename=\"selection.ply\"");
    res.set_content(reinterpret_cast<const char*>(ply.data()), ply.size(), "application/octet-stream");
  });
  svr.Post("/api/clear", [this, session, live, clients](const httplib::Request&, httplib::Response& res) {
    std::lock_guard<std::mutex> g(lock_);
    session().clear();
    send_json(res, {{"anchors", 0}, {"gaussians", 0}});
  });
  svr.Post("/api/visibility", [this, session, live, clients](const httplib::Request& req, httplib::Response& res) {
    const nlohmann::json body = parse_body(req);
    const Visibility v = parse_visibility(json_string(body, "selection"));
    std::lock_guard<std::mutex> g(lock_);
    session().set_visibility(v);
    send_json(res, {{"selection", visibility_name(v)}});
  });

  if (live) {
    svr.Get("/api/train", [live](const httplib::Request&, httplib::Response& res) { send_json(res, live->status()); });
    svr.Post("/api/train", [live](const httplib::Request& req, httplib::Response& res) {
      const nlohmann::json body = parse_body(req);
      if (!body.contains("paused") || !body["paused"].is_boolean())
        throw std::invalid_argument("give {\"paused\": true} to pause training, {\"paused\": false} to resume it");
      live->set_paused(body["paused"].get<bool>());
      send_json(res, live->status());
    });
  }
}

ViewServer::~ViewServer() = default;

int ViewServer::bind(const std::string& what) {
  int port = options_.port;
  if (port == 0) {
    port = svr_->bind_to_any_port(options_.host);
    if (port < 0) throw std::runtime_error("could not listen on " + options_.host + " (any port)");
  } else if (!svr_->bind_to_port(options_.host, port)) {
    throw std::runtime_error("could not listen on " + options_.host + ":" + std::to_string(port) +
                             " (in use, or not an address of this machine); choose another with --port N, or "
                             "--port 0 for any free one");
  }
  if (options_.host != "127.0.0.1" && options_.host != "localhost" && options_.host != "::1")
    spdlog::warn("listening on {}: other machines on the network can reach this viewer", options_.host);
  std::printf(
      "ag2gs view: serving %s at http://%s:%d/ (Ctrl-C to stop)\n", what.c_str(),
      options_.host.find(':') != std::string::npos ? ("[" + options_.host + "]").c_str() : options_.host.c_str(), port);
  std::fflush(stdout);

  return port;
}

void ViewServer::stop() {
  svr_->stop();
}

bool ViewServer::run() {
  std::atomic<bool> done{false};
  std::thread watcher([&] {
    while (!done) {
      if (InterruptGuard::interrupted()) {
        svr_->stop();
        return;
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
  });
  const bool ok = svr_->listen_after_bind();
  done = true;
  watcher.join();
  return ok || InterruptGuard::interrupted();
}

namespace {

void cmd_view(const GlobalOptions& global, const ViewArgs& a) {
  if (a.options.resolution < 0) throw std::invalid_argument("-r must be >= 1 (it divides the camera resolution)");
  InterruptGuard guard;
  InterruptGuard::set_stop_message("\nstopping the viewer\n");
  const auto t0 = std::chrono::steady_clock::now();
  Runtime rt(global.device);
  ViewSession session(rt, a.options);
  const nlohmann::json info0 = session.info();
  spdlog::info("device [{}] {}; {} anchors, {} Gaussians, {} views, text queries {}; ready in {:.1f} s",
               rt.info().index, rt.info().name, info0["anchors"].get<size_t>(), info0["gaussians"].get<size_t>(),
               info0["views"].size(), session.info()["text_queries"].get<bool>() ? "on" : "off (no --vocab)",
               std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
  ViewServer server([&session]() -> ViewSession& { return session; }, nullptr, a.serve);
  server.bind(a.options.model);
  const bool ok = server.run();
  if (InterruptGuard::interrupted()) {
    spdlog::info("stopped ({})", InterruptGuard::signal_name());
    return;
  }
  if (!ok) throw std::runtime_error("the server stopped unexpectedly");
}

}  // namespace

void register_view(CLI::App& app, GlobalOptions& global) {
  auto a = std::make_shared<ViewArgs>();
  auto* v = app.add_subcommand("view", "Serve a web page to look around a model and select objects interactively");
  v->add_option("model", a->options.model, "Model folder written by `ag2gs train` (MODEL_DIR/model.ag2gs)")->required();
  v->add_option("--scene", a->options.scene,
                "Scene directory the model was trained on: its training views to jump to and click in");
  v->add_option("--vocab", a->options.vocab, "Text vocabulary JSON {\"phrase\": [D floats], ...} for text queries");
  v->add_option("--port", a->serve.port, "TCP port (default 8080; 0 = any free port, printed)");
  v->add_option("--host", a->serve.host,
                "Address to listen on (default 127.0.0.1: this machine only; 0.0.0.0 opens it to the network)");
  v->add_option("--sparse", a->options.sparse,
                "COLMAP model folder inside the scene (default sparse/0/, else sparse/ when it holds the model)");
  v->add_option("-r,--resolution", a->options.resolution,
                "Divide the training views' cameras by R (default: the model's training -r)")
      ->check(CLI::Range(1, 64));
  set_action(v, [&global, a] { cmd_view(global, *a); });
}

}  // namespace ag2gs::cli
