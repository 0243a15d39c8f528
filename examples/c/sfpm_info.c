/*
 * sfpm_info: prints what a map holds through the sfpmap C API, one fact per line
 * ("key value ..."), then shows that bad input is reported, never a crash: a camera model
 * that does not exist, a query whose descriptor dimension does not fit level 0, a camera
 * wider than the localizer takes, and a session whose Lowe's ratio is out of range. A
 * session (the map's settings, level 0, a sequence) then runs the same query, before and
 * after the map handle is closed: the session holds the map.
 *
 *   cargo build --release --features capi
 *   cc -std=c11 -Wall -Wextra -Iinclude examples/c/sfpm_info.c -Ltarget/release -lsfpmap \
 *      -Wl,-rpath,"$PWD/target/release" -o sfpm_info
 *   ./sfpm_info spec/vectors/valid/levels.sfpm
 *
 * tests/api/embed_c.rs compiles and runs it against spec/vectors/valid/levels.sfpm.
 */
#include "sfpmap.h"

#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

/* IEEE binary16 bit pattern -> float (the map's descriptors are stored as f16). */
static float half_to_float(uint16_t h) {
  uint32_t sign = (uint32_t)(h >> 15) << 31, exp = (h >> 10) & 0x1f, man = h & 0x3ff;
  if (exp == 0) { /* zero or subnormal: man * 2^-24 */
    float f = ldexpf((float)man, -24);
    return sign ? -f : f;
  }
  if (exp == 31) return sign ? -INFINITY : (man ? NAN : INFINITY);
  float f = ldexpf((float)(man | 0x400), (int)exp - 25);
  return sign ? -f : f;
}

#define CHECK(call)                                                                  \
  do {                                                                               \
    SfpmStatus status_ = (call);                                                     \
    if (status_ != SFPM_OK) {                                                        \
      fprintf(stderr, "%s failed: %d: %s\n", #call, (int)status_, sfpm_last_error()); \
      return 1;                                                                      \
    }                                                                                \
  } while (0)

int main(int argc, char **argv) {
  if (argc != 2) {
    fprintf(stderr, "usage: %s MAP.sfpm\n", argv[0]);
    return 2;
  }
  printf("version %s\n", sfpm_version());

  SfpmMap map = 0;
  CHECK(sfpm_open(argv[1], &map));

  size_t n_levels = 0;
  CHECK(sfpm_level_count(map, &n_levels));
  printf("levels %zu\n", n_levels);
  uint16_t ids[64];
  size_t n_ids = 0;
  CHECK(sfpm_level_ids(map, ids, 64, &n_ids));
  for (size_t i = 0; i < n_ids && i < 64; i++) {
    SfpmLevelInfo info;
    CHECK(sfpm_level_info(map, ids[i], &info));
    printf("level %u dim_full %u dim_short %u points %llu has_rest %u\n", (unsigned)info.level,
           info.dim_full, info.dim_short, (unsigned long long)info.points, (unsigned)info.has_rest);

    const uint32_t *points = NULL;
    size_t n_points = 0;
    CHECK(sfpm_level_points(map, ids[i], &points, &n_points));
    if (n_points > 0) printf("level %u first_point %u\n", (unsigned)info.level, points[0]);

    if (info.has_descriptors && info.points > 0) {
      const uint16_t *shorts = NULL;
      size_t n_short = 0;
      CHECK(sfpm_level_desc_short(map, ids[i], &shorts, &n_short));
      printf("level %u short_len %zu short0 %.9g\n", (unsigned)info.level, n_short,
             half_to_float(shorts[0]));
      if (info.has_rest) {
        const uint16_t *rest = NULL;
        size_t n_rest = 0;
        CHECK(sfpm_level_desc_rest(map, ids[i], &rest, &n_rest));
        printf("level %u rest_len %zu rest0 %.9g\n", (unsigned)info.level, n_rest,
               half_to_float(rest[0]));
      }
    }
  }

  const float *positions = NULL;
  size_t n_points = 0;
  double origin[3];
  CHECK(sfpm_point_positions(map, &positions, &n_points, origin));
  printf("points %zu\n", n_points);
  printf("origin %.17g %.17g %.17g\n", origin[0], origin[1], origin[2]);
  if (n_points > 3)
    printf("position3 %.9g %.9g %.9g\n", positions[9], positions[10], positions[11]);

  size_t n_cameras = 0;
  CHECK(sfpm_camera_count(map, &n_cameras));
  printf("cameras %zu\n", n_cameras);
  for (size_t i = 0; i < n_cameras; i++) {
    char model[32];
    uint64_t width = 0, height = 0;
    double params[16];
    size_t n_params = 0;
    CHECK(sfpm_camera(map, i, model, sizeof model, &width, &height, params, 16, &n_params));
    printf("camera %zu %s %llu %llu params %zu first %.17g\n", i, model,
           (unsigned long long)width, (unsigned long long)height, n_params,
           n_params > 0 ? params[0] : 0.0);
  }

  size_t n_images = 0;
  CHECK(sfpm_image_count(map, &n_images));
  printf("images %zu\n", n_images);
  for (size_t i = 0; i < n_images; i++) {
    char name[256];
    size_t needed = 0;
    double pose[7];
    uint32_t camera = 0;
    CHECK(sfpm_image_name(map, i, name, sizeof name, &needed));
    CHECK(sfpm_image_pose(map, i, pose, &camera));
    printf("image %zu %s camera %u cam_from_world %.17g %.17g %.17g %.17g %.17g %.17g %.17g\n", i,
           name, camera, pose[0], pose[1], pose[2], pose[3], pose[4], pose[5], pose[6]);
  }

  const uint64_t *offsets = NULL;
  const uint32_t *seen = NULL;
  size_t n_offsets = 0, n_seen = 0;
  if (sfpm_visibility(map, &offsets, &n_offsets, &seen, &n_seen) == SFPM_OK) {
    printf("visibility offsets %zu entries %zu image0 %llu\n", n_offsets, n_seen,
           (unsigned long long)(offsets[1] - offsets[0]));
  }

  /* Bad input is reported, never a crash. */
  printf("null_out %d\n", (int)sfpm_level_count(map, NULL));
  printf("no_such_level %d\n", (int)sfpm_level_info(map, 999, &(SfpmLevelInfo){0}));
  double params[3] = {100.0, 32.0, 24.0};
  SfpmCamera bad_camera = {"NO_SUCH_MODEL", 64, 48, params, 3};
  SfpmLocalization found;
  float descriptor[4] = {1, 0, 0, 0};
  double keypoint[2] = {10.0, 10.0};
  printf("bad_camera %d\n",
         (int)sfpm_localize(map, keypoint, descriptor, 1, 4, &bad_camera, NULL, &found));

  /* A query with one 4-dimensional feature against level 0 (16 dims): SFPM_ERR_LOCALIZE. */
  SfpmCamera camera = {"SIMPLE_PINHOLE", 64, 48, params, 3};
  uint16_t level0 = 0;
  SfpmLocalizeOptions options = {&level0, 1, 0};
  SfpmStatus status = sfpm_localize(map, keypoint, descriptor, 1, 4, &camera, &options, &found);
  printf("localize %d inliers %llu\n", (int)status, (unsigned long long)found.inliers);

  /* Sizes are uint64_t, as sfpm_camera gives them; one above UINT32_MAX is refused (-3). */
  SfpmCamera too_wide = {"SIMPLE_PINHOLE", UINT64_C(1) << 32, 48, params, 3};
  printf("too_wide_camera %d\n",
         (int)sfpm_localize(map, keypoint, descriptor, 1, 4, &too_wide, &options, &found));

  /* A session: every setting, starting from the map's own, checked when it opens. */
  SfpmSessionOptions session_options;
  CHECK(sfpm_session_options_default(map, &session_options));
  printf("session_defaults ratio %.9g top_k %zu min_inliers %zu\n", (double)session_options.ratio,
         session_options.top_k, session_options.min_inliers);
  SfpmSessionOptions bad_ratio = session_options;
  bad_ratio.ratio = 1.5f;
  SfpmSession session = 0;
  status = sfpm_session_open(map, &bad_ratio, &session);
  printf("session_bad_ratio %d %s\n", (int)status, sfpm_last_error());

  session_options.levels = &level0;
  session_options.n_levels = 1;
  session_options.sequence = 1;
  CHECK(sfpm_session_open(map, &session_options, &session));
  uint8_t tracked = 0;
  status = sfpm_session_localize(session, keypoint, descriptor, 1, 4, &camera, &found, &tracked);
  printf("session_localize %d\n", (int)status);

  CHECK(sfpm_close(map));
  printf("double_close %d\n", (int)sfpm_close(map));
  printf("use_after_close %d\n", (int)sfpm_level_count(map, &n_levels));

  /* The session holds the map: still usable (the same dimension mismatch, -8). */
  status = sfpm_session_localize(session, keypoint, descriptor, 1, 4, &camera, &found, &tracked);
  printf("session_after_map_close %d\n", (int)status);
  CHECK(sfpm_session_close(session));
  printf("session_double_close %d\n", (int)sfpm_session_close(session));
  return 0;
}
