// Parsing JSON that came from outside the program (a selection, a model's
// header, a label or vocabulary file, a request to the viewer) with limits:
// nesting deeper than kJsonMaxDepth is refused before the parser sees it
// (nesting 100,000 levels deep crashed the program by exhausting the stack),
// and every parser error becomes one message naming the source.
#pragma once

#include <nlohmann/json.hpp>
#include <string>

namespace ag2gs {

constexpr int kJsonMaxDepth = 64;  // our files nest 4 levels at most

// The deepest nesting of [ and { in `text`, outside strings; stops counting
// (and returns) once it passes `stop_at`.
int json_nesting_depth(const std::string& text, int stop_at = kJsonMaxDepth);

// Parses `text`; throws std::runtime_error "<source>: ..." when it nests
// deeper than kJsonMaxDepth or is not valid JSON (numbers out of double's
// range included).
nlohmann::json parse_json_input(const std::string& text, const std::string& source);

// The parser's message for a user: without the library's "[json.exception.
// type_error.302] " code, e.g. "type must be number, but is string".
std::string json_error_text(const nlohmann::json::exception& e);

// Reads and parses the file at `path` (the message names the path; a folder
// or an unreadable file is refused as such).
nlohmann::json read_json_file(const std::string& path);

}  // namespace ag2gs
