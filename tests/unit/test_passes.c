/*
 * test_passes.c - EXR frames a compositor can use (issue 13, part 3): the
 * passes a job asks for (output.aovs), camera-space depth with misses far
 * away, world positions, Cryptomatte mattes and the standard header
 * attributes, checked on real renders (real Embree, real models from
 * /usr/share/assimp/models, jobs through the real parser) written as real
 * EXR files and read back with OpenEXR's C library and Debian's exrheader.
 *
 * The scene: two copies of the BCN dancer (objects "hero" and "double",
 * one asset "dancer") in front of a box scaled into a wall (object
 * "wall", asset "crate"), seen by a camera off every axis; the tangent
 * pass on scenes of its own.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <cjson/cJSON.h>
#include <math.h>
#include <openexr.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <unistd.h>

#include "asset/asset.h"
#include "job_json.h"
#include "microray.h"
#include "util/murmur3.h"

enum { W = 160, H = 120 };

#define SCENE(output)                                                                          \
    "{'name':'passes',"                                                                        \
    "'assets':{'dancer':{'path':'/usr/share/assimp/models/X/BCN_Epileptic.X'},"                \
    "          'crate':{'path':'/usr/share/assimp/models/OBJ/box.obj'}},"                      \
    "'objects':[{'name':'hero','asset':'dancer','pose':{'clip':0},"                            \
    "            'transform':{'translation':[-0.45,0,0]}},"                                    \
    "           {'name':'double','asset':'dancer','pose':{'clip':0,'offset':0.5},"             \
    "            'transform':{'translation':[0.05,0,0.5]}},"                                   \
    "           {'name':'wall','asset':'crate',"                                               \
    "            'transform':{'translation':[0,0,-0.8],'scale':[3.2,2.4,0.1]}}],"              \
    "'camera':{'yfov':42,'path':[{'t':0,'position':[0.9,0.45,3.6],'target':[0,0.05,0]}]},"     \
    "'frames':{'fps':30,'times':[0.4]}," output "}"

typedef struct rendered {
    mr_job *job;
    mr_film *film;
    mr_frame_stats st;
    char path[128];
} rendered;

static char g_dir[64];

/* Single quotes to double quotes (as test_job.c writes jobs). */
static char *dq(const char *s)
{
    char *t = strdup(s);
    assert_non_null(t);
    for (char *p = t; *p; p++)
        if (*p == '\'')
            *p = '"';
    return t;
}

/* Parses, renders frame `frame` (after the ones before it) and writes it
 * (as the renderers do: the meta of mr_exr_meta_for_frame) to
 * <dir>/<name>.exr. */
static rendered render_job_frame(const char *json, const char *name, size_t frame)
{
    rendered out;
    memset(&out, 0, sizeof out);
    char *text = dq(json);
    mr_job_error jerr = {0};
    mr_error err = {0};
    if (mr_job_parse(text, strlen(text), &out.job, &jerr) < 0)
        fail_msg("job: %s: %s", jerr.pointer, jerr.message);
    free(text);
    mr_asset *assets[4] = {NULL, NULL, NULL, NULL};
    assert_true(out.job->asset_count >= 1 && out.job->asset_count <= 4);
    for (size_t i = 0; i < out.job->asset_count; i++)
        if (mr_asset_load(out.job->assets[i].path, &assets[i], &err) < 0)
            fail_msg("%s", err.msg);
    mr_device *dev = NULL;
    mr_renderer *r = NULL;
    if (mr_device_new(0, &dev, &err) < 0 ||
        mr_renderer_new(dev, out.job, assets, NULL, &r, &err) < 0 ||
        mr_job_film_new(out.job, &out.film, &err) < 0)
        fail_msg("render: %s", err.msg);
    for (size_t k = 0; k <= frame; k++)
        if (mr_renderer_render(r, k, out.film, &out.st, &err) < 0)
            fail_msg("render frame %zu: %s", k, err.msg);
    mr_exr_meta meta;
    mr_exr_meta_for_frame(&meta, out.job, &out.st);
    snprintf(out.path, sizeof out.path, "%s/%s.exr", g_dir, name);
    if (mr_exr_write_file(out.path, out.film, &out.job->output.exr, &meta, &err) < 0)
        fail_msg("write: %s", err.msg);
    mr_renderer_free(r);
    mr_device_free(dev);
    for (size_t i = 0; i < 4; i++)
        mr_asset_free(assets[i]);
    return out;
}

static rendered render_job(const char *json, const char *name) { return render_job_frame(json, name, 0); }

static void rendered_free(rendered *r)
{
    mr_film_free(r->film);
    mr_job_free(r->job);
}

static char *run_capture(const char *cmd)
{
    FILE *p = popen(cmd, "r");
    size_t len = 0, cap = 1 << 16;
    char *buf = malloc(cap);
    assert_true(p && buf);
    for (size_t n; (n = fread(buf + len, 1, cap - len - 1, p)) > 0;) {
        len += n;
        if (cap - len < 4096) {
            cap *= 2;
            buf = realloc(buf, cap);
            assert_non_null(buf);
        }
    }
    buf[len] = '\0';
    pclose(p);
    return buf;
}

static char *exrheader(const char *path)
{
    char cmd[256];
    snprintf(cmd, sizeof cmd, "exrheader '%s' 2>&1", path);
    return run_capture(cmd);
}

/* The channel names exrheader lists, comma-joined in the file's order. */
static void channel_list(const char *header, char *out, size_t size)
{
    const char *p = strstr(header, "channels (type chlist):\n");
    out[0] = '\0';
    assert_non_null(p);
    p = strchr(p, '\n') + 1;
    while (strncmp(p, "    ", 4) == 0) {
        const char *comma = strchr(p, ',');
        assert_non_null(comma);
        if (out[0])
            strncat(out, ",", size - strlen(out) - 1);
        strncat(out, p + 4, (size_t)(comma - p - 4) < size - strlen(out) - 1
                                ? (size_t)(comma - p - 4)
                                : size - strlen(out) - 1);
        p = strchr(p, '\n') + 1;
    }
}

static exr_context_t open_exr(const char *path)
{
    exr_context_t ctxt = NULL;
    exr_context_initializer_t init = EXR_DEFAULT_CONTEXT_INITIALIZER;
    assert_int_equal(exr_start_read(&ctxt, path, &init), EXR_ERR_SUCCESS);
    return ctxt;
}

/* p (world) times an OpenEXR M44f (row vector), in double. */
static void row_mul(const float p[3], const exr_attr_m44f_t *m, double out[4])
{
    for (int c = 0; c < 4; c++)
        out[c] = p[0] * (double)m->m[c] + p[1] * (double)m->m[4 + c] + p[2] * (double)m->m[8 + c] +
                 (double)m->m[12 + c];
}

static int group_setup(void **state)
{
    (void)state;
    snprintf(g_dir, sizeof g_dir, "/tmp/mr_test_passes_XXXXXX");
    return mkdtemp(g_dir) ? 0 : -1;
}

static int group_teardown(void **state)
{
    char cmd[128];
    (void)state;
    snprintf(cmd, sizeof cmd, "rm -rf '%s'", g_dir);
    return getenv("MR_KEEP") ? 0 : system(cmd) == 0 ? 0 : -1;
}

/* The standard attributes, read back with OpenEXR: worldToCamera takes the
 * world point of every hit pixel (its P) to the camera-space point whose
 * z is that pixel's Z and whose x/z, y/z are its ray's direction;
 * worldToNDC takes it to the pixel's centre; misses read Z = 1e11 (far),
 * never 0. Tolerance: P and Z are floats of a scene 4 units across (about
 * 5e-7 absolute), so 2e-5 relative in depth and a hundredth of a pixel in
 * NDC hold with room; a wrong convention (ray distance for Z, a
 * transposed or un-flipped matrix) is off by percents or whole pixels. */
static void test_camera_attributes_and_depth(void **state)
{
    (void)state;
    rendered r = render_job(SCENE("'output':{'width':160,'height':120,'samples':2,"
                                  "'aovs':['rgba','z','p','id']}"),
                            "camera");
    exr_context_t ctxt = open_exr(r.path);
    exr_attr_m44f_t w2c, w2ndc;
    assert_int_equal(exr_attr_get_m44f(ctxt, 0, "worldToCamera", &w2c), EXR_ERR_SUCCESS);
    assert_int_equal(exr_attr_get_m44f(ctxt, 0, "worldToNDC", &w2ndc), EXR_ERR_SUCCESS);
    float sw = 0, par = 0;
    exr_attr_v2f_t swc;
    assert_int_equal(exr_get_screen_window_width(ctxt, 0, &sw), EXR_ERR_SUCCESS);
    assert_int_equal(exr_get_screen_window_center(ctxt, 0, &swc), EXR_ERR_SUCCESS);
    assert_int_equal(exr_get_pixel_aspect_ratio(ctxt, 0, &par), EXR_ERR_SUCCESS);
    /* the image's width on the z = 1 plane: 2 tan(yfov / 2) * aspect */
    assert_true(fabs(sw - 2.0 * tan(0.5 * 42.0 * M_PI / 180.0) * W / H) < 1e-5);
    assert_true(swc.x == 0.0f && swc.y == 0.0f && par == 1.0f);
    exr_attr_chromaticities_t chroma;
    assert_int_equal(exr_attr_get_chromaticities(ctxt, 0, "chromaticities", &chroma),
                     EXR_ERR_SUCCESS);
    assert_true(chroma.red_x == 0.64f && chroma.red_y == 0.33f && chroma.green_x == 0.30f &&
                chroma.green_y == 0.60f && chroma.blue_x == 0.15f && chroma.blue_y == 0.06f &&
                chroma.white_x == 0.3127f && chroma.white_y == 0.3290f);
    exr_attr_rational_t fps;
    assert_int_equal(exr_attr_get_rational(ctxt, 0, "framesPerSecond", &fps), EXR_ERR_SUCCESS);
    assert_true(fps.num == 30 && fps.denom == 1);
    const char *s = NULL;
    int32_t len = 0;
    float utc = 1;
    assert_int_equal(exr_attr_get_string(ctxt, 0, "owner", &len, &s), EXR_ERR_SUCCESS);
    assert_true(len > 0);
    assert_int_equal(exr_attr_get_string(ctxt, 0, "capDate", &len, &s), EXR_ERR_SUCCESS);
    /* YYYY:MM:DD hh:mm:ss */
    assert_int_equal(len, 19);
    assert_true(s[4] == ':' && s[7] == ':' && s[10] == ' ' && s[13] == ':' && s[16] == ':');
    assert_int_equal(exr_attr_get_float(ctxt, 0, "utcOffset", &utc), EXR_ERR_SUCCESS);
    assert_true(fabsf(utc) <= 14 * 3600 && fmodf(utc, 60) == 0);
    assert_int_equal(exr_attr_get_string(ctxt, 0, "comments", &len, &s), EXR_ERR_SUCCESS);
    assert_non_null(strstr(s, "job passes, frame 0"));
    exr_finish(&ctxt);

    mr_film *f = NULL;
    mr_error err = {0};
    assert_int_equal(mr_exr_read_file(r.path, &f, NULL, &err), MR_OK);
    size_t hits = 0, misses = 0;
    double worst_z = 0, worst_px = 0;
    for (int y = 0; y < H; y++)
        for (int x = 0; x < W; x++) {
            size_t i = (size_t)y * W + (size_t)x;
            if (!f->object_id[i]) {
                misses++;
                assert_true(f->z[i] == MR_DEPTH_MISS && f->px[i] == 0.0f);
                continue;
            }
            hits++;
            float p[3] = {f->px[i], f->py[i], f->pz[i]};
            double cam[4], ndc[4];
            row_mul(p, &w2c, cam);
            row_mul(p, &w2ndc, ndc);
            assert_true(fabs(cam[3] - 1.0) < 1e-12);
            assert_true(cam[2] > 0); /* in front: +z is the viewing direction */
            double dz = fabs(cam[2] - f->z[i]) / f->z[i];
            double nx = ndc[0] / ndc[3] * W - (x + 0.5), ny = ndc[1] / ndc[3] * H - (y + 0.5);
            worst_z = dz > worst_z ? dz : worst_z;
            worst_px = fmax(worst_px, fmax(fabs(nx), fabs(ny)));
            /* the direction: x/z, y/z on the z = 1 plane through the pixel */
            double sx = (2.0 * (x + 0.5) / W - 1) * 0.5 * sw, sy = (1 - 2.0 * (y + 0.5) / H) * 0.5 * sw * H / W;
            assert_true(fabs(cam[0] / cam[2] - sx) < 1e-4 && fabs(cam[1] / cam[2] - sy) < 1e-4);
        }
    if (worst_z > 2e-5 || worst_px > 0.01)
        fail_msg("worst depth error %.3g (relative), worst NDC error %.3g pixels", worst_z,
                 worst_px);
    /* The scene fills much of the frame but not all of it. */
    assert_true(hits > (size_t)W * H / 4 && misses > 100);
    mr_film_free(f);

    /* Debian's exrheader (the C++ library) reads and prints them. */
    char *h = exrheader(r.path);
    const char *want[] = {"worldToCamera (type m44f):", "worldToNDC (type m44f):",
                          "framesPerSecond (type rational): 30/1 (30)",
                          "chromaticities (type chromaticities):", "owner (type string):",
                          "capDate (type string):", "utcOffset (type float):",
                          "comments (type string):", "screenWindowWidth (type float):"};
    for (size_t k = 0; k < sizeof want / sizeof want[0]; k++)
        if (!strstr(h, want[k]))
            fail_msg("exrheader lacks \"%s\":\n%s", want[k], h);
    free(h);
    rendered_free(&r);
}

/* output.aovs: the file holds exactly the asked passes' channels, each
 * identical (bit for bit once decoded) to a render of every pass; passes
 * not asked are not traced either: without rgba no shadow ray is cast and
 * without rgba or cryptomatte only the pixel centre is. */
static void test_aovs_selection(void **state)
{
    (void)state;
    static const struct {
        const char *aovs;
        const char *channels; /* in the file's (sorted) order */
    } cases[] = {
        {"['rgba']", "A,B,G,R"},
        {"['z']", "Z"},
        {"['n','id']", "N.X,N.Y,N.Z,id.object,id.primitive"},
        {"['p','z']", "P.X,P.Y,P.Z,Z"},
        {"['t']", "T.X,T.Y,T.Z"},
        {"['cryptomatte']",
         "CryptoAsset00.A,CryptoAsset00.B,CryptoAsset00.G,CryptoAsset00.R,CryptoAsset01.A,"
         "CryptoAsset01.B,CryptoAsset01.G,CryptoAsset01.R,CryptoObject00.A,CryptoObject00.B,"
         "CryptoObject00.G,CryptoObject00.R,CryptoObject01.A,CryptoObject01.B,CryptoObject01.G,"
         "CryptoObject01.R"},
    };
    rendered all = render_job(SCENE("'output':{'width':160,'height':120,'samples':3,"
                                    "'aovs':['rgba','z','n','p','id','cryptomatte','t']}"),
                              "all");
    mr_film *full = NULL;
    mr_error err = {0};
    assert_int_equal(mr_exr_read_file(all.path, &full, NULL, &err), MR_OK);
    assert_int_equal(full->crypto_ranks, 4); /* 3 samples: 4 ranks, layers 00 and 01 */
    size_t n = (size_t)W * H;

    for (size_t c = 0; c < sizeof cases / sizeof cases[0]; c++) {
        char job[2048], name[16], got[1024];
        snprintf(job, sizeof job,
                 SCENE("'output':{'width':160,'height':120,'samples':3,'aovs':%s}"),
                 cases[c].aovs);
        snprintf(name, sizeof name, "sel%zu", c);
        rendered r = render_job(job, name);
        char *h = exrheader(r.path);
        channel_list(h, got, sizeof got);
        if (strcmp(got, cases[c].channels) != 0)
            fail_msg("aovs %s: channels %s, expected %s", cases[c].aovs, got, cases[c].channels);
        free(h);

        mr_film *back = NULL;
        assert_int_equal(mr_exr_read_file(r.path, &back, NULL, &err), MR_OK);
        unsigned a = r.job->output.aovs;
        assert_int_equal(r.film->aovs, a); /* the renderer kept only these */
        if (a & MR_AOV_RGBA) {
            assert_memory_equal(back->r, full->r, n * 4);
            assert_memory_equal(back->a, full->a, n * 4);
        }
        if (a & MR_AOV_Z)
            assert_memory_equal(back->z, full->z, n * 4);
        if (a & MR_AOV_N)
            assert_memory_equal(back->ny, full->ny, n * 4);
        if (a & MR_AOV_P)
            assert_memory_equal(back->px, full->px, n * 4);
        if (a & MR_AOV_T)
            assert_memory_equal(back->tz, full->tz, n * 4);
        if (a & MR_AOV_ID)
            assert_memory_equal(back->prim_id, full->prim_id, n * 4);
        if (a & MR_AOV_CRYPTOMATTE)
            for (int l = 0; l < MR_CRYPTO_LAYERS; l++)
                for (int k = 0; k < 8; k++)
                    assert_memory_equal(back->crypto[l][k], full->crypto[l][k], n * 4);
        /* traced: every sample with colour or Cryptomatte, else the centre
         * only; shadow rays only with colour */
        if (!(a & (MR_AOV_RGBA | MR_AOV_CRYPTOMATTE)))
            assert_int_equal(r.st.rays, (uint64_t)n);
        else if (!(a & MR_AOV_RGBA))
            assert_int_equal(r.st.rays, (uint64_t)n * 3);
        else
            assert_true(r.st.rays > (uint64_t)n * 3);
        mr_film_free(back);
        rendered_free(&r);
    }
    mr_film_free(full);
    rendered_free(&all);
}

/* normals: "half" stores N.* as HALF, each the float normal rounded to the
 * nearest half (check_half's bound: relative 2^-11). */
static void test_half_normals(void **state)
{
    (void)state;
    rendered r = render_job(SCENE("'output':{'width':160,'height':120,'aovs':['n'],"
                                  "'normals':'half'}"),
                            "halfn");
    char *h = exrheader(r.path);
    assert_non_null(strstr(h, "    N.X, 16-bit floating-point, sampling 1 1\n"));
    assert_non_null(strstr(h, "    N.Z, 16-bit floating-point, sampling 1 1\n"));
    free(h);
    mr_film *back = NULL;
    mr_error err = {0};
    assert_int_equal(mr_exr_read_file(r.path, &back, NULL, &err), MR_OK);
    size_t changed = 0;
    for (size_t i = 0; i < (size_t)W * H; i++) {
        float want = r.film->nx[i], got = back->nx[i];
        assert_true(fabsf(got - want) <= fabsf(want) * ldexpf(1.0f, -11) + ldexpf(1.0f, -25));
        changed += got != want;
    }
    assert_true(changed > 100); /* rounded, not stored as float */
    mr_film_free(back);
    rendered_free(&r);
}

/* Cryptomatte: per layer the header names it, its hash and conversion and
 * a manifest mapping every name to its id (the float bits of the name's
 * MurmurHash3 with the clamped exponent), under the key made of the layer
 * name's hash; in the pixels, rank 0 of the object layer is the object the
 * pixel's centre hits wherever all samples hit one object (coverage 1),
 * the asset layer merges objects of one asset, and a pixel's coverages
 * add up to its alpha (the background is transparent). */
static void test_cryptomatte(void **state)
{
    (void)state;
    rendered r = render_job(SCENE("'output':{'width':160,'height':120,'samples':4,"
                                  "'aovs':['rgba','id','cryptomatte']}"),
                            "crypto");
    exr_context_t ctxt = open_exr(r.path);
    static const char *const layers[2] = {"CryptoObject", "CryptoAsset"};
    static const char *const names[2][3] = {{"hero", "double", "wall"}, {"dancer", "crate", NULL}};
    for (int l = 0; l < 2; l++) {
        char key[16], attr[64];
        const char *s = NULL;
        int32_t len = 0;
        snprintf(key, sizeof key, "%08x",
                 (unsigned)mr_murmur3_32(layers[l], strlen(layers[l]), 0));
        key[7] = '\0';
        snprintf(attr, sizeof attr, "cryptomatte/%s/name", key);
        assert_int_equal(exr_attr_get_string(ctxt, 0, attr, &len, &s), EXR_ERR_SUCCESS);
        assert_string_equal(s, layers[l]);
        snprintf(attr, sizeof attr, "cryptomatte/%s/hash", key);
        assert_int_equal(exr_attr_get_string(ctxt, 0, attr, &len, &s), EXR_ERR_SUCCESS);
        assert_string_equal(s, "MurmurHash3_32");
        snprintf(attr, sizeof attr, "cryptomatte/%s/conversion", key);
        assert_int_equal(exr_attr_get_string(ctxt, 0, attr, &len, &s), EXR_ERR_SUCCESS);
        assert_string_equal(s, "uint32_to_float32");
        snprintf(attr, sizeof attr, "cryptomatte/%s/manifest", key);
        assert_int_equal(exr_attr_get_string(ctxt, 0, attr, &len, &s), EXR_ERR_SUCCESS);
        cJSON *m = cJSON_Parse(s);
        assert_non_null(m);
        assert_int_equal(cJSON_GetArraySize(m), l == 0 ? 3 : 2);
        for (int k = 0; k < 3 && names[l][k]; k++) {
            const cJSON *v = cJSON_GetObjectItemCaseSensitive(m, names[l][k]);
            char hex[16];
            assert_true(cJSON_IsString(v));
            snprintf(hex, sizeof hex, "%08x", (unsigned)mr_cryptomatte_id_bits(names[l][k]));
            assert_string_equal(v->valuestring, hex);
        }
        cJSON_Delete(m);
    }
    exr_finish(&ctxt);

    mr_film *f = NULL;
    mr_error err = {0};
    assert_int_equal(mr_exr_read_file(r.path, &f, NULL, &err), MR_OK);
    assert_int_equal(f->crypto_ranks, 4);
    float obj_id[3], dancer = mr_cryptomatte_id("dancer"), crate = mr_cryptomatte_id("crate");
    for (int k = 0; k < 3; k++)
        obj_id[k] = mr_cryptomatte_id(names[0][k]);
    size_t whole = 0, mixed = 0;
    for (size_t i = 0; i < (size_t)W * H; i++) {
        for (int l = 0; l < 2; l++) {
            float sum = 0;
            for (int k = 0; k < 4; k++) {
                sum += f->crypto[l][2 * k + 1][i];
                if (k && f->crypto[l][2 * k + 1][i] > f->crypto[l][2 * k - 1][i])
                    fail_msg("pixel %zu layer %d: ranks out of order", i, l);
            }
            if (fabsf(sum - f->a[i]) > 1e-6f)
                fail_msg("pixel %zu layer %d: coverage %g, alpha %g", i, l, sum, f->a[i]);
        }
        uint32_t o = f->object_id[i];
        if (o && f->crypto[MR_CRYPTO_OBJECT][1][i] == 1.0f) {
            whole++;
            assert_memory_equal(&f->crypto[MR_CRYPTO_OBJECT][0][i], &obj_id[o - 1], 4);
            assert_true(f->crypto[MR_CRYPTO_OBJECT][2][i] == 0 &&
                        f->crypto[MR_CRYPTO_OBJECT][3][i] == 0);
            float want = o == 3 ? crate : dancer;
            assert_memory_equal(&f->crypto[MR_CRYPTO_ASSET][0][i], &want, 4);
            assert_true(f->crypto[MR_CRYPTO_ASSET][1][i] == 1.0f);
        }
        /* hero and double overlap: two object ranks, one asset rank */
        float c0 = f->crypto[MR_CRYPTO_OBJECT][0][i], c1 = f->crypto[MR_CRYPTO_OBJECT][2][i];
        if ((c0 == obj_id[0] && c1 == obj_id[1]) || (c0 == obj_id[1] && c1 == obj_id[0])) {
            mixed++;
            assert_memory_equal(&f->crypto[MR_CRYPTO_ASSET][0][i], &dancer, 4);
            assert_true(f->crypto[MR_CRYPTO_ASSET][1][i] ==
                        f->crypto[MR_CRYPTO_OBJECT][1][i] + f->crypto[MR_CRYPTO_OBJECT][3][i]);
        }
    }
    assert_true(whole > 1000);
    assert_true(mixed > 0); /* the scene has the case the asset layer must merge */
    mr_film_free(f);

    char *h = exrheader(r.path);
    assert_non_null(strstr(h, "(type string): \"CryptoObject\""));
    assert_non_null(strstr(h, "(type string): \"MurmurHash3_32\""));
    free(h);
    rendered_free(&r);
}

/* Background: transparent unless the job asks (premultiplied colour over
 * nothing); an asked-for opaque background keeps its colour. */
static void test_background_alpha(void **state)
{
    (void)state;
    rendered clear = render_job(SCENE("'output':{'width':160,'height':120,'aovs':['rgba','id']}"),
                                "clear");
    rendered opaque = render_job(
        SCENE("'background':{'color':[0.25,0.5,1],'alpha':1},"
              "'output':{'width':160,'height':120,'aovs':['rgba','id']}"),
        "opaque");
    size_t misses = 0;
    for (size_t i = 0; i < (size_t)W * H; i++) {
        if (clear.film->object_id[i])
            continue;
        misses++;
        assert_true(clear.film->r[i] == 0 && clear.film->g[i] == 0 && clear.film->b[i] == 0 &&
                    clear.film->a[i] == 0);
        assert_true(opaque.film->r[i] == 0.25f && opaque.film->g[i] == 0.5f &&
                    opaque.film->b[i] == 1.0f && opaque.film->a[i] == 1.0f);
    }
    assert_true(misses > 100);
    rendered_free(&clear);
    rendered_free(&opaque);
}

/* A packet's colour sums over samples when some of them miss: the
 * integrator sums the samples that hit nothing before any sample of the
 * packet hit once for all its pixels, and each pixel's own only once one
 * hits (integrator.c). Checked against what a pixel must hold whatever
 * the order: with 3 samples, a background of alpha 0.25 and Cryptomatte,
 * whose coverages are the fraction c of the pixel's samples that hit,
 * alpha is c + (1 - c) 0.25 (1e-6: a few float roundings of sums below
 * 1), which a sample's miss dropped or counted twice moves by 1/12; a
 * pixel no sample hits holds the background's premultiplied colour; and
 * the colour is the same bit for bit without Cryptomatte, where a packet
 * that hits nothing takes its colour in one go. */
static void test_missed_samples_sum(void **state)
{
    (void)state;
#define OUT(aovs)                                                                              \
    "'background':{'color':[0.25,0.5,1],'alpha':0.25},"                                        \
    "'output':{'width':160,'height':120,'samples':3,'aovs':" aovs "}"
    rendered crypto = render_job(SCENE(OUT("['rgba','id','cryptomatte']")), "misses-crypto");
    rendered plain = render_job(SCENE(OUT("['rgba','id']")), "misses-plain");
#undef OUT
    const mr_film *f = crypto.film;
    size_t none = 0, some = 0;
    for (size_t i = 0; i < (size_t)W * H; i++) {
        float c = 0;
        for (int k = 0; k < f->crypto_ranks; k++)
            c += f->crypto[MR_CRYPTO_OBJECT][2 * k + 1][i];
        if (fabsf(f->a[i] - (c + (1 - c) * 0.25f)) > 1e-6f)
            fail_msg("pixel %zu: alpha %g, coverage %g", i, f->a[i], c);
        if (c == 0) {
            none++;
            assert_true(f->r[i] == 0.0625f && f->g[i] == 0.125f && f->b[i] == 0.25f);
        } else if (c < 1) {
            some++;
        }
        assert_memory_equal(&plain.film->r[i], &f->r[i], 4);
        assert_memory_equal(&plain.film->g[i], &f->g[i], 4);
        assert_memory_equal(&plain.film->b[i], &f->b[i], 4);
        assert_memory_equal(&plain.film->a[i], &f->a[i], 4);
    }
    assert_true(none > 1000); /* the background */
    assert_true(some > 100);  /* silhouettes: samples that miss beside ones that hit */
    rendered_free(&crypto);
    rendered_free(&plain);
}

/* |T| of pixel i. */
static double tangent_len(const mr_film *f, size_t i)
{
    return sqrt((double)f->tx[i] * f->tx[i] + (double)f->ty[i] * f->ty[i] + (double)f->tz[i] * f->tz[i]);
}

/* The tangent pass (output.aovs "t", paper 001 3.3.4), on a frame of
 * objects that all have tangents: the skinned, posed dancer (mesh kind,
 * its texture coordinates' tangents skinned with it) and Wuson as a
 * spring-mass object bent by a probe (its tangents carried by the
 * curvature mapping), with aovs ["rgba", "t"] at one sample (alpha then
 * says whether the pixel's centre ray hit). Read back through OpenEXR's C
 * library (mr_exr_read_file) and listed by exrheader: T.X T.Y T.Z are
 * FLOAT, unit where the ray hit (1e-6: one float normalisation) and 0
 * where it missed. On the passes' scene, whose wall is a box without
 * texture coordinates, the wall's pixels are 0 and the dancers' unit. */
static void test_tangent_pass(void **state)
{
    (void)state;
    rendered r = render_job_frame(
        "{'name':'tangents',"
        "'assets':{'dancer':{'path':'/usr/share/assimp/models/X/BCN_Epileptic.X'},"
        "          'wuson':{'path':'/usr/share/assimp/models/PLY/Wuson.ply'}},"
        "'objects':[{'name':'hero','asset':'dancer','pose':{'clip':0},"
        "            'transform':{'translation':[-0.6,0,0]}},"
        "           {'name':'dough','asset':'wuson','kind':'springmass',"
        "            'transform':{'translation':[0.7,0,0],'scale':[0.6,0.6,0.6]},"
        "            'springmass':{'nodes':400,'pins':[{'box_max':[2,0.2,2]}],"
        "              'probes':[{'radius':0.15,'path':[{'t':0,'position':[0.7,1.2,0]},"
        "                                               {'t':0.2,'position':[0.7,0.8,0.05]}]}]}}],"
        "'camera':{'yfov':42,'path':[{'t':0,'position':[0.1,0.6,2.4],'target':[0,0.45,0]}]},"
        "'frames':{'fps':24,'start':0,'end':0.25},"
        "'output':{'width':160,'height':120,'samples':1,'aovs':['rgba','t']}}",
        "tangents", 5); /* frame 5: 75 steps, the probe pressed in */
    char *h = exrheader(r.path);
    char got[256];
    channel_list(h, got, sizeof got);
    assert_string_equal(got, "A,B,G,R,T.X,T.Y,T.Z");
    assert_non_null(strstr(h, "    T.X, 32-bit floating-point, sampling 1 1\n"));
    free(h);
    mr_film *back = NULL;
    mr_error err = {0};
    assert_int_equal(mr_exr_read_file(r.path, &back, NULL, &err), MR_OK);
    assert_true(back->tx && back->ty && back->tz);
    size_t hits = 0, misses = 0, side[2] = {0, 0};
    double worst = 0;
    for (size_t i = 0; i < (size_t)W * H; i++) {
        if (back->a[i] == 1.0f) {
            worst = fmax(worst, fabs(tangent_len(back, i) - 1));
            hits++;
            side[i % W >= W / 2]++; /* the dancer left, the dough right */
        } else {
            assert_true(back->a[i] == 0.0f);
            if (back->tx[i] != 0.0f || back->ty[i] != 0.0f || back->tz[i] != 0.0f)
                fail_msg("pixel %zu missed but has a tangent (%g %g %g)", i, back->tx[i], back->ty[i], back->tz[i]);
            misses++;
        }
    }
    printf("tangent pass: %zu hits (%zu left, %zu right; |T| within %.2e of 1), %zu misses\n", hits, side[0],
           side[1], worst, misses);
    assert_true(side[0] > 1000 && side[1] > 1000 && misses > 2000);
    if (!(worst < 1e-6))
        fail_msg("a hit's tangent is %.3g off unit length", worst);
    mr_film_free(back);
    rendered_free(&r);

    /* objects without tangents: the wall (box.obj has no uvs) */
    r = render_job(SCENE("'output':{'width':160,'height':120,'aovs':['t','id']}"), "notan");
    size_t wall = 0, dancers = 0;
    for (size_t i = 0; i < (size_t)W * H; i++) {
        double l = tangent_len(r.film, i);
        if (r.film->object_id[i] == 3) {
            assert_true(l == 0);
            wall++;
        } else if (r.film->object_id[i] != 0) {
            assert_true(fabs(l - 1) < 1e-6);
            dancers++;
        }
    }
    assert_true(wall > 1000 && dancers > 1000);
    rendered_free(&r);
}

/* The tangent pass of a mesh object agrees with its asset's tangents
 * (asset.h, mr_mesh_tangents) at the hit: the spider (a rigid model whose
 * 19 meshes share vertices, so tangents vary across triangles) placed by
 * a rotation, a non-uniform scale and a translation. Per hit pixel: the
 * triangle (id.primitive, over the meshes in order), the barycentric
 * coordinates of P in the placed triangle, the corners' tangents placed
 * (moved by the transform's linear part and fitted to their placed
 * normals, as skinning places them) and interpolated with them, made
 * orthogonal to N and unit: T within 1e-3 of that (the barycentric
 * coordinates recovered from a float P are off by about 1e-7 of the
 * coordinates over the triangle's size, and the tangents of a triangle's
 * corners differ by up to a radian or so; measured: 1.2e-4). */
static void test_tangent_pass_matches_asset(void **state)
{
    (void)state;
    rendered r = render_job(
        "{'name':'spider',"
        "'assets':{'spider':{'path':'/usr/share/assimp/models/OBJ/spider.obj'}},"
        "'objects':[{'name':'spider','asset':'spider',"
        "            'transform':{'translation':[0.1,-0.05,0],'rotation':[0.2,0.3,0.1,0.927],"
        "                         'scale':[0.012,0.009,0.01]}}],"
        "'camera':{'yfov':45,'path':[{'t':0,'position':[0.4,1.6,2.6],'target':[0,0,0]}]},"
        "'frames':{'fps':10,'times':[0]},"
        "'output':{'width':160,'height':120,'aovs':['t','n','p','id']}}",
        "spider");
    mr_asset *a = NULL;
    mr_error err = {0};
    assert_int_equal(mr_asset_load(r.job->assets[0].path, &a, &err), MR_OK);
    for (size_t k = 0; k < a->node_count; k++) /* OBJ: meshes placed by identity nodes */
        for (int e = 0; e < 16; e++)
            assert_true(a->nodes[k].local.m[e] == (e % 5 == 0 ? 1.0f : 0.0f));
    const mr_mat4 *M = &r.job->objects[0].transform;
    const mr_mat4 N = mr_mat4_normal_matrix(M);
    const mr_film *f = r.film;
    size_t hits = 0;
    double worst = 0;
    for (size_t i = 0; i < (size_t)W * H; i++) {
        if (f->object_id[i] == 0)
            continue;
        hits++;
        uint32_t prim = f->prim_id[i];
        size_t mi = 0;
        while (prim >= a->meshes[mi].triangle_count)
            prim -= a->meshes[mi++].triangle_count;
        const mr_mesh *m = &a->meshes[mi];
        assert_non_null(m->tangents);
        const uint32_t *q = &m->indices[(size_t)prim * 3];
        double P[3][3], p[3] = {f->px[i], f->py[i], f->pz[i]};
        for (int k = 0; k < 3; k++) {
            mr_vec3 w = mr_mat4_point(M, mr_v3(m->positions[q[k] * 3], m->positions[q[k] * 3 + 1],
                                               m->positions[q[k] * 3 + 2]));
            P[k][0] = w.x, P[k][1] = w.y, P[k][2] = w.z;
        }
        /* barycentric coordinates of p in the placed triangle (least squares) */
        double e1[3], e2[3], d[3];
        for (int c = 0; c < 3; c++)
            e1[c] = P[1][c] - P[0][c], e2[c] = P[2][c] - P[0][c], d[c] = p[c] - P[0][c];
        double d00 = 0, d01 = 0, d11 = 0, d20 = 0, d21 = 0;
        for (int c = 0; c < 3; c++) {
            d00 += e1[c] * e1[c], d01 += e1[c] * e2[c], d11 += e2[c] * e2[c];
            d20 += d[c] * e1[c], d21 += d[c] * e2[c];
        }
        double den = d00 * d11 - d01 * d01;
        double bu = (d11 * d20 - d01 * d21) / den, bv = (d00 * d21 - d01 * d20) / den, bw = 1 - bu - bv;
        /* each corner's tangent placed (moved by M, fitted to its placed
         * normal, unit; in double), then interpolated */
        double want[3] = {0, 0, 0}, n[3] = {f->nx[i], f->ny[i], f->nz[i]}, bary[3] = {bw, bu, bv};
        for (int k = 0; k < 3; k++) {
            const float *tk = &m->tangents[q[k] * 4], *nk = &m->normals[q[k] * 3];
            mr_vec3 tm = mr_mat4_dir(M, mr_v3(tk[0], tk[1], tk[2]));
            mr_vec3 nm = mr_mat4_dir(&N, mr_v3(nk[0], nk[1], nk[2]));
            double tw[3] = {tm.x, tm.y, tm.z}, nw[3] = {nm.x, nm.y, nm.z}, nn = 0, tn = 0, tl = 0;
            for (int c = 0; c < 3; c++)
                nn += nw[c] * nw[c];
            for (int c = 0; c < 3; c++)
                tn += tw[c] * nw[c] / nn;
            for (int c = 0; c < 3; c++) {
                tw[c] -= tn * nw[c];
                tl += tw[c] * tw[c];
            }
            for (int c = 0; c < 3; c++)
                want[c] += bary[k] * tw[c] / sqrt(tl);
        }
        double along = want[0] * n[0] + want[1] * n[1] + want[2] * n[2], len = 0;
        for (int c = 0; c < 3; c++) {
            want[c] -= along * n[c];
            len += want[c] * want[c];
        }
        len = sqrt(len);
        double got[3] = {f->tx[i], f->ty[i], f->tz[i]}, off = 0;
        for (int c = 0; c < 3; c++)
            off = fmax(off, fabs(got[c] - want[c] / len));
        worst = fmax(worst, off);
    }
    printf("spider: %zu hit pixels, tangent pass within %.2e of the asset's tangents at the hits\n", hits,
           worst);
    assert_true(hits > 1500);
    if (!(worst < 1e-3))
        fail_msg("the tangent pass is %.3g off the asset's tangent at a hit", worst);
    mr_asset_free(a);
    rendered_free(&r);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_camera_attributes_and_depth),
        cmocka_unit_test(test_aovs_selection),
        cmocka_unit_test(test_half_normals),
        cmocka_unit_test(test_cryptomatte),
        cmocka_unit_test(test_background_alpha),
        cmocka_unit_test(test_missed_samples_sum),
        cmocka_unit_test(test_tangent_pass),
        cmocka_unit_test(test_tangent_pass_matches_asset),
    };
    return cmocka_run_group_tests_name("passes", tests, group_setup, group_teardown);
}
