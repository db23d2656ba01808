// Every setting of a removal (RemovalSettings, apps/removal/removal.h)
// declared once, as the training settings are (host/core/settings.h): its
// field, its key in `remove --print-config` and removal.json, its flag and
// help, and the range it must lie in. RemovalSettings' to_json and validate
// and `remove`'s flags loop over this table; the default of each field is
// its initialiser.
#pragma once

#include <vector>

#include "host/core/settings.h"

namespace ag2gs {

struct RemovalSettings;
using RemovalSetting = Setting<RemovalSettings>;

// The table, in --help's order.
const std::vector<RemovalSetting>& removal_settings();

}  // namespace ag2gs
