// Every setting of a query (QueryConfig, queries/query.h) declared once, as
// the training settings are (host/core/settings.h): its field, its key in
// `query --print-config` and selection.json's thresholds, its flag (on
// `query`, `remove` and `simulate`, which select the same way) and help, and
// the range it must lie in. QueryConfig's to_json and validate and the
// commands' flags loop over this table; the default of each field is its
// initialiser.
#pragma once

#include <vector>

#include "host/core/settings.h"

namespace ag2gs {

struct QueryConfig;
using QuerySetting = Setting<QueryConfig>;

// The table, in --help's order.
const std::vector<QuerySetting>& query_settings();

}  // namespace ag2gs
