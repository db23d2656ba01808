// Device runtime: device selection, the program cache (memory and disk,
// corrupt entries rebuilt), build errors carrying the log, growable buffers,
// per-kernel timing.
#include <gtest/gtest.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <regex>
#include <sstream>

#include "host/device/cl_runtime.h"
#include "host/device/device_policy.h"
#include "host/device/kernel_call.h"
#include "host/device/kernel_source.h"
#include "tests/io_test_util.h"
#include "tests/test_util.h"

namespace fs = std::filesystem;

namespace ag2gs {
namespace {

fs::path fresh_dir(const std::string& name) {
  fs::path d = fs::path(testing::TempDir()) / ("ag2gs_rt_" + name + "_" + std::to_string(::getpid()));
  fs::remove_all(d);
  fs::create_directories(d);
  return d;
}

TEST(Runtime, ListsAtLeastOneDeviceAndSelectsTheDefault) {
  auto devices = list_devices();
  ASSERT_FALSE(devices.empty()) << "no OpenCL device: is pocl-opencl-icd installed?";
  int def = default_device_index(devices);
  EXPECT_GE(def, 0);
  EXPECT_EQ(resolve_device_index(-1, devices), def);
  EXPECT_THROW(resolve_device_index(static_cast<int>(devices.size()), devices), std::runtime_error);
}

TEST(Runtime, BadDeviceEnvironmentVariableIsRejected) {
  auto devices = list_devices();
  setenv("AG2GS_DEVICE", "gpu0", 1);
  EXPECT_THROW(resolve_device_index(-1, devices), std::runtime_error);
  setenv("AG2GS_DEVICE", "99", 1);
  try {
    resolve_device_index(-1, devices);
    FAIL();
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("ag2gs devices"), std::string::npos) << e.what();
  }
  unsetenv("AG2GS_DEVICE");
}

TEST(Runtime, DiskCacheIsWrittenReusedAndCorruptEntriesRebuilt) {
  fs::path dir = fresh_dir("cache");
  setenv("AG2GS_CACHE_DIR", dir.c_str(), 1);
  std::map<std::string, std::string> defs{{"SCAN_BLOCK", "64"}, {"SCAN_WG", "64"}};
  {
    Runtime rt;
    rt.kernel("bin.cl", "iota", defs);
  }
  std::vector<fs::path> files;
  for (auto& e : fs::directory_iterator(dir)) files.push_back(e.path());
  ASSERT_EQ(files.size(), 1u) << "one cache entry expected";
  auto size = fs::file_size(files[0]);
  EXPECT_GT(size, 64u);
  // Corrupt the entry: flip bytes in the middle (the checksum must catch it).
  {
    std::fstream f(files[0], std::ios::in | std::ios::out | std::ios::binary);
    f.seekp(static_cast<std::streamoff>(size / 2));
    char junk[16] = {'x', 'x', 'x', 'x', 'x', 'x', 'x', 'x', 'x', 'x', 'x', 'x', 'x', 'x', 'x', 'x'};
    f.write(junk, sizeof junk);
  }
  {
    Runtime rt;
    cl::Kernel k = rt.kernel("bin.cl", "iota", defs);  // must rebuild, not crash
    EXPECT_NE(k(), nullptr);
  }
  // Truncated entry, too.
  fs::resize_file(files[0], 20);
  {
    Runtime rt;
    EXPECT_NO_THROW(rt.kernel("bin.cl", "iota", defs));
  }
  EXPECT_GT(fs::file_size(files[0]), 64u) << "the rebuilt program was written back";
  for (auto& e : fs::directory_iterator(dir))
    EXPECT_EQ(e.path().string().find(".tmp."), std::string::npos) << "temp file left behind: " << e.path();
  unsetenv("AG2GS_CACHE_DIR");
  fs::remove_all(dir);
}

// Kernels build with -w (PoCL's ABI warnings on CPUs without AVX-512 would
// print "N warnings generated." into every log); AG2GS_KERNEL_WARNINGS=1
// keeps the compiler's warnings in the build log.
TEST(Runtime, KernelWarningsOnlyWhenAskedFor) {
  fs::path dir = fresh_dir("kernels_warn");
  std::ofstream(dir / "layout.h") << kernel_source("layout.h");
  std::ofstream(dir / "common.cl") << kernel_source("common.cl");
  std::ofstream(dir / "warns.cl")
      << "#warning ag2gs_test_marker\n__kernel void warns(__global float* x) { x[0] = 1.f; }\n";
  setenv("AG2GS_KERNEL_DIR", dir.c_str(), 1);
  setenv("AG2GS_NO_KERNEL_CACHE", "1", 1);
  for (const char* asked : {"", "1"}) {
    SCOPED_TRACE(asked);
    if (*asked)
      setenv("AG2GS_KERNEL_WARNINGS", asked, 1);
    else
      unsetenv("AG2GS_KERNEL_WARNINGS");
    Runtime rt;
    cl::Program p = rt.program("warns.cl", {});
    const std::string log = p.getBuildInfo<CL_PROGRAM_BUILD_LOG>(rt.info().device);
    EXPECT_EQ(log.find("ag2gs_test_marker") != std::string::npos, *asked != 0) << log;
  }
  unsetenv("AG2GS_KERNEL_WARNINGS");
  unsetenv("AG2GS_KERNEL_DIR");
  unsetenv("AG2GS_NO_KERNEL_CACHE");
}

TEST(Runtime, BuildFailureCarriesNameOptionsAndLog) {
  fs::path dir = fresh_dir("kernels");
  std::ofstream(dir / "layout.h") << kernel_source("layout.h");
  std::ofstream(dir / "common.cl") << kernel_source("common.cl");
  std::ofstream(dir / "broken.cl") << "__kernel void broken(__global float* x) { x[0] = undefined_name; }\n";
  setenv("AG2GS_KERNEL_DIR", dir.c_str(), 1);
  setenv("AG2GS_NO_KERNEL_CACHE", "1", 1);
  Runtime rt;
  try {
    rt.program("broken.cl", {{"MY_DEFINE", "3"}});
    FAIL() << "expected a BuildError";
  } catch (const BuildError& e) {
    std::string m = e.what();
    EXPECT_NE(m.find("broken.cl"), std::string::npos) << m;
    EXPECT_NE(m.find("-cl-std=CL1.2"), std::string::npos) << m;
    EXPECT_NE(m.find("MY_DEFINE"), std::string::npos) << m;
    EXPECT_NE(m.find("undefined_name"), std::string::npos) << "build log missing: " << m;
  }
  // A missing file names itself and the fix.
  try {
    rt.program("missing.cl", {});
    FAIL();
  } catch (const std::runtime_error& e) {
    EXPECT_NE(std::string(e.what()).find("missing.cl"), std::string::npos);
  }
  unsetenv("AG2GS_KERNEL_DIR");
  unsetenv("AG2GS_NO_KERNEL_CACHE");
  fs::remove_all(dir);
}

TEST(Runtime, CheckMacroNamesTheCallAndLocation) {
  try {
    AG2GS_CL_CHECK(CL_INVALID_VALUE);
    FAIL();
  } catch (const ClError& e) {
    std::string m = e.what();
    EXPECT_NE(m.find("CL_INVALID_VALUE"), std::string::npos) << m;
    EXPECT_NE(m.find("test_runtime.cpp:"), std::string::npos) << m;
    EXPECT_EQ(e.code(), CL_INVALID_VALUE);
  }
}

TEST(Runtime, BuffersGrowAndTimingsAreRecorded) {
  Runtime rt;
  rt.set_profiling(true);
  DeviceBuffer b(&rt);
  EXPECT_TRUE(b.reserve(1000));
  EXPECT_FALSE(b.reserve(500)) << "a smaller request must not reallocate";
  EXPECT_TRUE(b.reserve(100000));
  EXPECT_GE(b.capacity(), 100000u);
  EXPECT_GE(rt.peak_bytes(), 100000u);
  std::vector<uint32_t> out;
  cl::Kernel k = rt.kernel("bin.cl", "iota", {{"SCAN_BLOCK", "64"}, {"SCAN_WG", "64"}});
  k.setArg(0, 1000);
  k.setArg(1, b.get());
  rt.launch("iota", k, cl::NDRange(1000), cl::NDRange(64));
  b.download(out, 1000);
  for (uint32_t i = 0; i < 1000; ++i) ASSERT_EQ(out[i], i);
  auto t = rt.take_timings();
  ASSERT_EQ(t.count("iota"), 1u);
  EXPECT_GE(t["iota"], 0.0);
  // Growth: geometric on devices, to the size asked on a simulator.
  const size_t before = b.capacity();
  EXPECT_TRUE(b.reserve(before + 4));
  if (rt.exact_allocations())
    EXPECT_EQ(b.capacity(), before + 4);
  else
    EXPECT_GE(b.capacity(), before + before / 2);
  // Released memory leaves the runtime's count; the next reserve allocates
  // afresh and the buffer works as before.
  const uint64_t held = rt.allocated_bytes();
  const size_t cap = b.capacity();
  b.release();
  EXPECT_EQ(b.capacity(), 0u);
  EXPECT_EQ(rt.allocated_bytes(), held - cap);
  b.release();  // twice is harmless
  EXPECT_EQ(rt.allocated_bytes(), held - cap);
  EXPECT_TRUE(b.reserve(4000));
  EXPECT_EQ(rt.allocated_bytes(), held - cap + b.capacity());
  k.setArg(1, b.get());
  rt.launch("iota", k, cl::NDRange(1000), cl::NDRange(64));
  b.download(out, 1000);
  for (uint32_t i = 0; i < 1000; ++i) ASSERT_EQ(out[i], i);
}

// Each launch's arguments are checked against the kernel's own declaration:
// iota(int n, __global uint* out). A buffer where the count goes, a float
// for the int, or one argument too few are refused, naming the kernel and
// the parameter, before anything runs; the right call passes.
TEST(Runtime, KernelArgumentsAreCheckedAgainstTheDeclaration) {
  Runtime rt;
  DeviceBuffer b(&rt);
  b.reserve(64 * sizeof(uint32_t));
  cl::Kernel k = rt.kernel("bin.cl", "iota", {{"SCAN_BLOCK", "64"}, {"SCAN_WG", "64"}});
  const std::shared_ptr<const KernelSignature> sig = kernel_signature(k);
  EXPECT_EQ(sig->kernel, "iota");
  EXPECT_EQ(sig->num_args, 2u);
  test::expect_error_with<std::invalid_argument>([&] { set_kernel_args(k, 64); }, {"iota", "takes 2", "passed 1"});
  // PoCL reports arg info (also for kernels loaded from the cache); where a
  // device does not, the count alone is checked.
  if (rt.info().platform.find("Portable Computing Language") != std::string::npos) {
    ASSERT_EQ(sig->params.size(), 2u);
    EXPECT_EQ(sig->params[1].name, "out");
  }
  if (sig->params.size() == 2) {
    EXPECT_EQ(sig->params[0].type, "int");
    test::expect_error_with<std::invalid_argument>([&] { set_kernel_args(k, b, 64); },
                                                   {"iota", "argument 0", "a buffer"});
    test::expect_error_with<std::invalid_argument>([&] { set_kernel_args(k, 64.f, b); },
                                                   {"argument 0", "int", "a scalar float"});
    test::expect_error_with<std::invalid_argument>([&] { set_kernel_args(k, 64, 7); }, {"argument 1", "uint*"});
  }
  set_kernel_args(k, 64, b);
  rt.launch("iota", k, cl::NDRange(64), cl::NDRange(64));
  std::vector<uint32_t> out;
  b.download(out, 64);
  for (uint32_t i = 0; i < 64; ++i) ASSERT_EQ(out[i], i);
}

// KernelCall sets arguments by name: a name that is not the parameter at
// its position, a buffer smaller than the bytes the kernel reaches, or a
// missing argument are refused naming the kernel; the right call runs.
TEST(Runtime, KernelCallChecksNamesAndBufferSizes) {
  Runtime rt;
  DeviceBuffer b(&rt);
  b.reserve(64 * sizeof(uint32_t));
  cl::Kernel k = rt.kernel("bin.cl", "iota", {{"SCAN_BLOCK", "64"}, {"SCAN_WG", "64"}});
  if (!kernel_signature(k)->params.empty())
    test::expect_error_with<std::invalid_argument>([&] { KernelCall(k).arg("count", 64); },
                                                   {"iota", "argument 0", "'int n'", "'count'"});
  test::expect_error_with<std::logic_error>([&] { KernelCall(k).arg("n", 64).buffer("out", b, 65 * 4); },
                                            {"iota", "'out'", "256 bytes", "reaches 260"});
  test::expect_error_with<std::invalid_argument>([&] { KernelCall(k).arg("n", 64).done(); }, {"iota", "takes 2"});
  KernelCall(k).arg("n", 64).buffer("out", b, 64 * 4).done();
  rt.launch("iota", k, cl::NDRange(64), cl::NDRange(64));
  std::vector<uint32_t> out;
  b.download(out, 64);
  for (uint32_t i = 0; i < 64; ++i) ASSERT_EQ(out[i], i);
}

// PoCL's headers rename the builtin functions by macro (#define step
// _cl_step), and with them a parameter of the same name: the signature keeps
// the name the kernel declares.
TEST(Runtime, KernelSignatureNamesAParameterLikeABuiltinAsDeclared) {
  Runtime rt;
  cl::Kernel k = rt.kernel("anchor_growth.cl", "growth_accumulate", {});
  const std::shared_ptr<const KernelSignature> sig = kernel_signature(k);
  if (sig->params.empty()) GTEST_SKIP() << "the device reports no argument names";
  EXPECT_EQ(sig->params[5].name, "step");
}

// A store to one component of a vector element of a buffer (ranges[t].x = i)
// may be compiled as a load and a store of the whole vector; two work-items
// writing the two halves then lose one of the values. NVIDIA's OpenCL does
// this (tile_ranges broke every render of more than one tile there), while
// PoCL and Oclgrind store the component alone, so no run here can catch it:
// the kernels must not contain the pattern.
std::vector<std::string> component_stores(const std::string& source) {
  static const std::regex store(
      R"((\w+\s*\[[^\]\n]*\])\s*\.\s*(x|y|z|w|s[0-9a-fA-F]+|lo|hi|even|odd)\s*([-+*/|&^]?=)(?!=))");
  std::vector<std::string> hits;
  std::istringstream lines(source);
  std::string line;
  for (int n = 1; std::getline(lines, line); ++n)
    if (std::regex_search(line, store)) hits.push_back(std::to_string(n) + ": " + line);
  return hits;
}

TEST(KernelSource, NoKernelStoresIntoOneComponentOfABufferVector) {
  // The check itself: it finds the old tile_ranges store and lets reads,
  // comparisons and private vectors pass.
  EXPECT_EQ(component_stores("  if (i == 0) ranges[t].x = i;\n  out[2 * i].s3 += v;").size(), 2u);
  EXPECT_TRUE(component_stores("  int2 r = ranges[t];\n  r.x = 1;\n  if (ranges[t].x == 0) {}\n").empty());
  size_t files = 0;
  for (const auto& entry : fs::directory_iterator(fs::path(test::source_dir()) / "kernels")) {
    if (entry.path().extension() != ".cl" && entry.path().extension() != ".h") continue;
    ++files;
    std::ifstream in(entry.path());
    std::stringstream text;
    text << in.rdbuf();
    for (const auto& hit : component_stores(text.str()))
      ADD_FAILURE() << entry.path().filename().string() << ":" << hit;
  }
  EXPECT_GT(files, 10u);
}

}  // namespace
}  // namespace ag2gs
