/*
 * bench_speckle.c - shading artefacts of every example against the same
 * scene as triangle meshes (issue 13 part 1). Not a test: it prints figures
 * and never fails.
 *
 * For each examples/<name>.json (sorted) the job is rendered as it is and
 * as triangles: the same file with every object turned into plain mesh
 * objects (kind and kind block dropped; a displaced object keeps its
 * block with method "tessellated", its exact micro-triangles; an svo object becomes one mesh
 * object per instance, with the instance's transform and pose, or the rest
 * pose for method "rigid", which ignores poses). Same camera, lights,
 * frames and poses; shadows on whatever the example says (the artefacts are
 * mostly shadow acne). The metric's interior pixels are those whose 8
 * neighbours hit one object; an svo object's instances are one object (one
 * id.object), so in its triangle version the mesh objects made from one
 * svo object count as one object too: otherwise the edges where one
 * instance passes in front of another would be interior only in the voxel
 * rendering. Reported per example, over all its frames:
 *  - the median isolated-dark-pixel rate (mr_film_speckles, the
 *    `speckle_pct` of every frame's stats) of the example and of its
 *    triangle version, and their ratio (issue 13's goal: <= 1.2);
 *  - strays: pixels the example hits more than one pixel away from the
 *    triangle version's silhouette (mr_film_compare, summed over frames;
 *    goal 0 for dmm) and holes, the converse.
 * An example whose poses name joints the triangle mesh does not have (svo
 * skeletons extract their own bones), or that is triangles already (a
 * spring-mass surface is its mapped mesh's triangles), has no triangle
 * version and is reported alone.
 *
 * usage: bench_speckle [--examples a,b,...] [--frames N]  (from the
 * repository root; --frames renders every k-th frame so at most N per
 * example, default all)
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include <cJSON.h>

#include "microray.h"
#include "files.h"
#include "job_json.h"
#include "bench_util.h"

#define MAX_EXAMPLES 64
#define MAX_FRAMES 512
#define MAX_OBJECTS 4096

static void die(const char *what, const char *msg)
{
    fprintf(stderr, "bench_speckle: %s: %s\n", what, msg);
    exit(1);
}

/* The triangle version of one object, appended to out; false when there
 * is none. group[k] gets the index of the example's object that triangle
 * object k comes from (k counted over out). */
static bool to_triangles(const cJSON *o, cJSON *out, uint32_t *group, uint32_t source)
{
    int first = cJSON_GetArraySize(out);
    const cJSON *kind = cJSON_GetObjectItem(o, "kind");
    const char *k = cJSON_IsString(kind) ? kind->valuestring : "mesh";
    if (strcmp(k, "springmass") == 0)
        return false; /* traced as its own triangles already; without its kind it was the mesh unsimulated */
    if (strcmp(k, "svo") != 0) {
        cJSON *m = cJSON_Duplicate(o, true);
        cJSON *block = cJSON_GetObjectItem(m, k);
        if (strcmp(k, "displaced") == 0 && cJSON_IsObject(block)) {
            cJSON_DeleteItemFromObject(block, "method");
            cJSON_AddStringToObject(block, "method", "tessellated");
        } else {
            cJSON_DeleteItemFromObject(m, "kind");
            cJSON_DeleteItemFromObject(m, k);
        }
        cJSON_AddItemToArray(out, m);
        if (first < MAX_OBJECTS)
            group[first] = source;
        return true;
    }
    const cJSON *svo = cJSON_GetObjectItem(o, "svo");
    const cJSON *method = cJSON_GetObjectItem(svo, "method");
    bool rigid = !cJSON_IsString(method) || strcmp(method->valuestring, "rigid") == 0;
    if (cJSON_IsTrue(cJSON_GetObjectItem(svo, "skeleton")) ||
        cJSON_IsObject(cJSON_GetObjectItem(svo, "skeleton")))
        return false; /* poses name the extracted bones */
    if (cJSON_GetObjectItem(o, "transform"))
        return false; /* not composed here; no example needs it */
    const cJSON *instances = cJSON_GetObjectItem(svo, "instances");
    int count = cJSON_IsArray(instances) ? cJSON_GetArraySize(instances) : 1;
    for (int i = 0; i < count; i++) {
        const cJSON *inst = cJSON_IsArray(instances) ? cJSON_GetArrayItem(instances, i) : NULL;
        cJSON *m = cJSON_CreateObject();
        cJSON_AddItemToObject(m, "asset", cJSON_Duplicate(cJSON_GetObjectItem(o, "asset"), true));
        const cJSON *color = cJSON_GetObjectItem(o, "color");
        if (color)
            cJSON_AddItemToObject(m, "color", cJSON_Duplicate(color, true));
        const cJSON *t = inst ? cJSON_GetObjectItem(inst, "transform") : NULL;
        if (t)
            cJSON_AddItemToObject(m, "transform", cJSON_Duplicate(t, true));
        const cJSON *pose = inst ? cJSON_GetObjectItem(inst, "pose") : NULL;
        if (!pose)
            pose = cJSON_GetObjectItem(o, "pose");
        if (pose && !rigid)
            cJSON_AddItemToObject(m, "pose", cJSON_Duplicate(pose, true));
        cJSON_AddItemToArray(out, m);
        if (first + i < MAX_OBJECTS)
            group[first + i] = source;
    }
    return true;
}

/* Asset paths relative to the job file (as microrayd render reads them). */
static void resolve_paths(mr_job *job, const char *job_path)
{
    const char *slash = strrchr(job_path, '/');
    int dir = slash ? (int)(slash - job_path) : 1;
    for (size_t i = 0; i < job->asset_count; i++) {
        char *p = job->assets[i].path;
        if (!p || p[0] == '/')
            continue;
        size_t n = (size_t)dir + strlen(p) + 2;
        char *abs = malloc(n);
        if (!abs)
            die(job_path, "out of memory");
        snprintf(abs, n, "%.*s/%s", dir, slash ? job_path : ".", p);
        free(p);
        job->assets[i].path = abs;
    }
}

/* The example as parsed: shadows on; and its triangle version (NULL when
 * it has none), with group[k]: the example's object triangle object k
 * comes from. */
static void load_jobs(const char *path, mr_job **job, mr_job **tri, uint32_t *group)
{
    char *text;
    size_t len;
    mr_error err = {0};
    if (mr_file_read(path, MR_JOB_MAX_BYTES, &text, &len, &err) < 0)
        die(path, err.msg);
    cJSON *doc = cJSON_ParseWithLength(text, len);
    free(text);
    if (!doc)
        die(path, "not JSON");
    cJSON *output = cJSON_GetObjectItem(doc, "output");
    if (!output)
        cJSON_AddItemToObject(doc, "output", output = cJSON_CreateObject());
    cJSON_DeleteItemFromObject(output, "shadows");
    cJSON_AddTrueToObject(output, "shadows");
    cJSON *objects = cJSON_CreateArray(), *o;
    bool convertible = true;
    uint32_t source = 0;
    cJSON_ArrayForEach(o, cJSON_GetObjectItem(doc, "objects"))
        convertible = convertible && to_triangles(o, objects, group, source++);
    if (cJSON_GetArraySize(objects) > MAX_OBJECTS)
        die(path, "too many objects as triangles");
    char *as_is = cJSON_PrintUnformatted(doc);
    cJSON_ReplaceItemInObject(doc, "objects", objects);
    char *as_tri = cJSON_PrintUnformatted(doc);
    cJSON_Delete(doc);
    mr_job_error jerr = {0};
    if (mr_job_parse(as_is, strlen(as_is), job, &jerr) < 0)
        die(path, jerr.message);
    *tri = NULL;
    if (convertible && mr_job_parse(as_tri, strlen(as_tri), tri, &jerr) < 0)
        die(path, jerr.message);
    free(as_is);
    free(as_tri);
    resolve_paths(*job, path);
    if (*tri)
        resolve_paths(*tri, path);
}

static mr_asset **load_assets(const mr_job *job)
{
    mr_asset **assets = calloc(job->asset_count, sizeof *assets);
    if (!assets)
        die("assets", "out of memory");
    for (size_t i = 0; i < job->asset_count; i++)
        assets[i] = bench_load_asset(&job->assets[i], job->assets[i].refine_params.threads);
    return assets;
}

static void free_assets(mr_asset **assets, size_t n)
{
    for (size_t i = 0; i < n; i++)
        mr_asset_free(assets[i]);
    free(assets);
}

static bool wanted(const char *name, const char *list)
{
    if (!list)
        return true;
    size_t n = strlen(name);
    for (const char *s = list; (s = strstr(s, name)); s += n)
        if ((s == list || s[-1] == ',') && (s[n] == ',' || s[n] == '\0'))
            return true;
    return false;
}

typedef struct row {
    char name[128];
    size_t frames;
    double pct, tri_pct;
    size_t strays, holes;
    bool has_tri;
} row;

/* id.object of the film's triangle objects -> that of the example's object
 * each comes from (1-based, 0 a miss), so both renderings have the same
 * objects for mr_film_speckles. */
static void group_objects(mr_film *f, const uint32_t *group, size_t objects)
{
    size_t n = (size_t)f->width * (size_t)f->height;
    for (size_t i = 0; i < n; i++)
        if (f->object_id[i] > 0 && f->object_id[i] <= objects)
            f->object_id[i] = group[f->object_id[i] - 1] + 1;
}

static row measure(const char *name, const char *path, int max_frames)
{
    row res = {.frames = 0};
    snprintf(res.name, sizeof res.name, "%s", name);
    mr_job *job[2];
    static uint32_t group[MAX_OBJECTS];
    load_jobs(path, &job[0], &job[1], group);
    res.has_tri = job[1] != NULL;
    int modes = res.has_tri ? 2 : 1;
    mr_device *dev = NULL;
    mr_error err = {0};
    if (mr_device_new(0, &dev, &err) < 0)
        die("device", err.msg);
    mr_asset **assets = load_assets(job[0]);
    mr_renderer *r[2] = {0};
    mr_film *film[2] = {0};
    for (int m = 0; m < modes; m++)
        if (mr_renderer_new(dev, job[m], assets, NULL, &r[m], &err) < 0 ||
            mr_film_new(job[m]->output.width, job[m]->output.height, &film[m], &err) < 0)
            die(name, err.msg);
    size_t count = job[0]->frame_count, step = 1;
    if (max_frames > 0 && count > (size_t)max_frames)
        step = (count + (size_t)max_frames - 1) / (size_t)max_frames;
    double pct[2][MAX_FRAMES];
    for (size_t f = 0; f < count && res.frames < MAX_FRAMES; f += step, res.frames++) {
        mr_frame_stats st[2];
        for (int m = 0; m < modes; m++) {
            if (mr_renderer_render(r[m], f, film[m], &st[m], &err) < 0)
                die(name, err.msg);
            pct[m][res.frames] = st[m].speckle_pct;
        }
        if (res.has_tri && job[1]->object_count != job[0]->object_count) {
            mr_speckle_result sp;
            group_objects(film[1], group, job[1]->object_count);
            mr_film_speckles(film[1], &sp);
            pct[1][res.frames] = sp.speckle_pct;
        }
        if (res.has_tri) {
            mr_compare_result c;
            if (mr_film_compare(film[0], film[1], st[1].scene_diagonal, &c, &err) < 0)
                die(name, err.msg);
            res.strays += c.strays;
            res.holes += c.holes;
        }
    }
    res.pct = median(pct[0], (int)res.frames);
    res.tri_pct = res.has_tri ? median(pct[1], (int)res.frames) : 0;
    for (int m = 0; m < modes; m++) {
        mr_film_free(film[m]);
        mr_renderer_free(r[m]);
    }
    free_assets(assets, job[0]->asset_count);
    for (int m = 0; m < modes; m++)
        mr_job_free(job[m]);
    mr_device_free(dev);
    return res;
}

int main(int argc, char **argv)
{
    const char *list = NULL;
    int max_frames = 0;
    for (int i = 1; i < argc; i++) {
        if (strcmp(argv[i], "--examples") == 0 && i + 1 < argc) {
            list = argv[++i];
        } else if (strcmp(argv[i], "--frames") == 0 && i + 1 < argc) {
            max_frames = atoi(argv[++i]);
        } else {
            fprintf(stderr, "usage: bench_speckle [--examples a,b,...] [--frames N]\n");
            return 2;
        }
    }
    char *all[MAX_EXAMPLES], *names[MAX_EXAMPLES];
    size_t count = bench_examples(all, MAX_EXAMPLES);
    int n = 0;
    for (size_t i = 0; i < count; i++)
        if (wanted(all[i], list))
            names[n++] = all[i];
        else
            free(all[i]);
    printf("\n## Shading artefacts (issue 13): isolated dark pixels of every example against "
           "the same scene as triangle meshes, shadows on, median over its frames\n\n"
           "| example | frames | speckle %% | as triangles %% | ratio | strays | holes |\n"
           "|---|---|---|---|---|---|---|\n");
    for (int i = 0; i < n; i++) {
        char path[512];
        snprintf(path, sizeof path, "examples/%s.json", names[i]);
        row x = measure(names[i], path, max_frames);
        if (x.has_tri)
            printf("| %s | %zu | %.3f | %.3f | %.2f | %zu | %zu |\n", x.name, x.frames, x.pct,
                   x.tri_pct, x.tri_pct > 0 ? x.pct / x.tri_pct : 0.0, x.strays, x.holes);
        else
            printf("| %s | %zu | %.3f | - | - | - | - |\n", x.name, x.frames, x.pct);
        fflush(stdout);
        free(names[i]);
    }
    printf("\nstrays: pixels an example hits more than one pixel away from its triangle "
           "version's silhouette (summed over frames); holes: the converse.\n");
    return 0;
}
