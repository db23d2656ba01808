// `ag2gs train`'s flags: the training settings' from their table
// (train/train_settings.h), the presets, and the run's own (stages, stage
// 3, progress, the live viewer, checkpoints).
#include <spdlog/spdlog.h>

#include <algorithm>
#include <cstdio>
#include <limits>
#include <memory>
#include <string>

#include "cli/setting_options.h"
#include "cli/train_command.h"
#include "train/stage3/stage3_settings.h"

namespace ag2gs::cli {

std::string flag_text(const TrainSetting& s, const TrainConfig& c) {
  const nlohmann::json v = s.get(c);
  if (s.is_bool() && !s.takes_value) {
    const std::string name = s.name_for(v.get<bool>());
    return name.empty() ? s.flag_name() + "=" + (v.get<bool>() ? "true" : "false") : name;
  }
  if (s.is_bool()) return s.flag_name() + (v.get<bool>() ? " true" : " false");
  if (v.is_number_float()) return fmt::format("{} {:g}", s.flag_name(), v.get<double>());
  return s.flag_name() + " " + v.dump();
}

namespace {

// --preset's help, from the table.
std::string preset_help() {
  std::string def, paper;
  const TrainConfig d = TrainConfig::preset("default"), p = TrainConfig::preset("paper");
  for (const TrainSetting& s : train_settings()) {
    if (s.in_default) def += " " + flag_text(s, d);
    if (s.in_paper) paper += " " + flag_text(s, p);
  }
  return "default (= appearance, the measured setting for photographed scenes:" + def +
         ") or paper (the method as published:" + paper +
         ", 5 children inside their voxels, one seeded layer); the library's defaults for the rest; flags given "
         "explicitly win";
}

}  // namespace

void apply_preset(const CLI::App& sub, TrainArgs& a, bool log) {
  const bool continues = a.resume || std::find(a.stages.begin(), a.stages.end(), 1) == a.stages.end();
  if (continues && sub.count("--preset") == 0) return;
  apply_train_preset(a.config, a.preset, [&sub](const TrainSetting& s) { return sub.count(s.flag_name()) > 0; });
  if (!log) return;
  std::string line;
  for (const TrainSetting& s : train_settings())
    if (s.in_a_preset() && !(s.auto_value && s.get(a.config) == *s.auto_value))  // a rule's value: no flag gives it
      line += " " + flag_text(s, a.config);
  spdlog::info("preset {}:{}", a.preset, line);
}

void register_train(CLI::App& app, GlobalOptions& global) {
  auto a = std::make_shared<TrainArgs>();
  TrainConfig& c = a->config;
  auto* sub = app.add_subcommand("train",
                                 "Train the anchor model on a scene directory: stage 1 (appearance, masks), stage 2 "
                                 "(propagation loss), stage 3 (clusters, language features); writes "
                                 "MODEL_DIR/model.ag2gs and MODEL_DIR/point_cloud.ply");
  add_scene_options(sub, *a);
  add_setting_options(sub, train_settings(), c);
  add_progress_options(sub, *a);
  sub->add_flag("--view", a->view,
                "Serve the viewer while training (as `ag2gs view`): the picture follows the model, with its progress "
                "and a pause button; after training it shows the final model until Ctrl-C");
  sub->add_option("--port", a->serve.port, "With --view: TCP port (default 8080; 0 = any free port, printed)")
      ->check(CLI::Range(0, 65535));
  sub->add_option("--host", a->serve.host, "With --view: address to listen on (default 127.0.0.1)");
  sub->add_option("--save-every", a->save_every, "Checkpoint every N iterations (default 0 = end only)")
      ->check(non_negative_number());
  sub->add_flag("--resume", a->resume,
                "Continue from MODEL_DIR/checkpoint.ag2gs (its settings, stages included; flags given must agree "
                "with them)");
  sub->add_flag("--force", a->force,
                "Start a new model even though MODEL_DIR holds one (its files are replaced when training ends)");
  sub->add_option("--stages", a->stages,
                  "Stages to run (comma-separated, default 1,2,3); without 1 they run on MODEL_DIR's checkpoint / "
                  "model (e.g. --stages 3 re-clusters a trained model)")
      ->delimiter(',')
      ->check(CLI::Range(1, 3));
  add_setting_options(sub, stage3_settings(), a->stage3);
  sub->add_option("--preset", a->preset, preset_help())->check(CLI::IsMember({"default", "appearance", "paper"}));
  auto print_config = std::make_shared<bool>(false);
  sub->add_flag("--print-config", *print_config,
                "Print the settings this command would train with (the preset, then the flags given; JSON, the "
                "`config` of model.ag2gs) and exit without reading the scene or writing anything");
  set_action(sub, [&global, a, sub, print_config] {
    a->stages_given = sub->count("--stages") > 0;
    apply_preset(*sub, *a, !*print_config);
    if (*print_config) {
      a->config.validate();
      std::printf("%s\n", a->config.to_json().dump(2).c_str());
      return;
    }
    cmd_train(global, *a);
  });
}

}  // namespace ag2gs::cli
