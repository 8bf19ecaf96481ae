/*
 * test_reference_passes.c - which reference passes a job gets and what
 * each draws (render/reference.c over the kinds' `reference` ops, kind.h),
 * from parsed jobs alone (nothing imported, nothing rendered; the renders
 * are tests/integration/test_reference.c):
 *  - per kind, the passes an object asking for references gets: mesh and
 *    springmass "tessellated" (themselves), dmm and displaced both, svo
 *    "ground_truth" only, none for an svo with an extracted skeleton, none
 *    beyond the tessellation for displaced at mip level 0 or springmass
 *    mapped trilinearly;
 *  - what each pass draws: the parameter overrides (dmm mode
 *    "tessellated" keeping the deformation; displaced method "tessellated"
 *    and level 0 or twice the range; springmass "trilinear"), the asset as
 *    plain triangles (dmm, svo: one object per instance, its transform
 *    after the object's, its pose or the object's, rigid ones at rest),
 *    objects that do not ask drawn as they are, an object without a
 *    ground truth drawn as its tessellation in that pass; no object of a
 *    pass asks for passes of its own, and the pass keeps only the passes
 *    the comparison reads;
 *  - the job's and the objects' flags: the job's is the default, an
 *    object's own wins.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <stdio.h>
#include <string.h>

#include "job_json.h"
#include "kinds/displaced/displaced_kind.h"
#include "kinds/dmm/dmm_kind.h"
#include "kinds/springmass/springmass_kind.h"
#include "kinds/svo/svo_kind.h"
#include "render/reference.h"

#define T (1u << MR_REFERENCE_TESSELLATED)
#define G (1u << MR_REFERENCE_GROUND_TRUTH)

static mr_job *parse(const char *root, const char *objects)
{
    char text[4096];
    snprintf(text, sizeof text,
             "{%s\"assets\":{\"m\":{\"path\":\"/a.gltf\"},\"tex\":{\"path\":\"/t.png\"}},"
             "\"objects\":[%s],"
             "\"camera\":{\"path\":[{\"t\":0,\"position\":[0,0,5],\"target\":[0,0,0]}]},"
             "\"frames\":{\"times\":[0,1]}}",
             root, objects);
    mr_job *job = NULL;
    mr_job_error e = {0};
    if (mr_job_parse(text, strlen(text), &job, &e) < 0)
        fail_msg("%s: %s at %s", text, e.message, e.pointer);
    return job;
}

static unsigned passes_of(const char *root, const char *objects)
{
    mr_job *job = parse(root, objects);
    unsigned passes = 99;
    mr_error err = {0};
    assert_int_equal(mr_job_reference_passes(job, &passes, &err), MR_OK);
    mr_job_free(job);
    return passes;
}

static void test_passes_per_kind(void **state)
{
    (void)state;
    const char *on = "\"reference\":true,";
    assert_int_equal(passes_of("", "{\"asset\":\"m\"}"), 0);
    assert_int_equal(passes_of(on, "{\"asset\":\"m\"}"), T);
    assert_int_equal(passes_of(on, "{\"asset\":\"m\",\"kind\":\"dmm\",\"dmm\":{\"mode\":\"base\"}}"), T | G);
    assert_int_equal(passes_of(on, "{\"asset\":\"m\",\"kind\":\"svo\"}"), G);
    assert_int_equal(passes_of(on, "{\"asset\":\"m\",\"kind\":\"displaced\",\"displaced\":"
                                   "{\"texture\":\"tex\",\"level\":2}}"),
                     T | G);
    assert_int_equal(passes_of(on, "{\"asset\":\"m\",\"kind\":\"displaced\",\"displaced\":"
                                   "{\"texture\":\"tex\"}}"),
                     T);
    assert_int_equal(passes_of(on, "{\"asset\":\"m\",\"kind\":\"displaced\",\"displaced\":"
                                   "{\"procedural\":{\"example\":\"tex\"},\"range\":64}}"),
                     T | G);
    assert_int_equal(passes_of(on, "{\"asset\":\"m\",\"kind\":\"springmass\"}"), T | G);
    assert_int_equal(passes_of(on, "{\"asset\":\"m\",\"kind\":\"springmass\",\"springmass\":"
                                   "{\"mapping\":\"trilinear\"}}"),
                     T);
    /* the object's flag wins over the job's */
    assert_int_equal(passes_of(on, "{\"asset\":\"m\",\"kind\":\"svo\"},{\"asset\":\"m\","
                                   "\"kind\":\"dmm\",\"reference\":false}"),
                     G);
    assert_int_equal(passes_of("", "{\"asset\":\"m\"},{\"asset\":\"m\",\"kind\":\"svo\","
                                   "\"reference\":true}"),
                     G);
    assert_int_equal(passes_of("\"reference\":false,", "{\"asset\":\"m\",\"reference\":true}"), T);
}

/* Pass `type` of the job, which must be present. */
static void pass_of(const mr_job *job, mr_reference_type type, mr_reference_pass *p)
{
    bool present = false;
    mr_error err = {0};
    assert_int_equal(mr_reference_pass_init(job, type, p, &present, &err), MR_OK);
    assert_true(present);
    assert_int_equal(p->job.output.aovs, MR_AOV_REFERENCE);
    assert_false(p->job.reference);
    for (size_t i = 0; i < p->job.object_count; i++)
        assert_false(p->job.objects[i].reference);
    assert_int_equal(p->job.frame_count, job->frame_count);
}

static void test_what_passes_draw(void **state)
{
    (void)state;
    /* 0: dmm asking; 1: a mesh that does not ask; 2: displaced at level 0
     * (no ground truth: its tessellation there) */
    mr_job *job = parse("", "{\"asset\":\"m\",\"kind\":\"dmm\",\"dmm\":{\"mode\":\"interpolated\","
                            "\"level\":3},\"reference\":true,\"color\":[0.1,0.2,0.3]},"
                            "{\"asset\":\"m\"},"
                            "{\"asset\":\"m\",\"kind\":\"displaced\",\"displaced\":{\"texture\":"
                            "\"tex\",\"method\":\"raymarch\"},\"reference\":true}");
    mr_reference_pass p;
    pass_of(job, MR_REFERENCE_TESSELLATED, &p);
    assert_int_equal(p.job.object_count, 3);
    const mr_dmm_params *d = p.job.objects[0].params, *src = job->objects[0].params;
    assert_ptr_equal(p.job.objects[0].kind, &mr_kind_dmm);
    assert_int_equal(d->mode, MR_DMM_TESSELLATED);
    assert_int_equal(d->deform, MR_DMM_DEFORM_INTERPOLATED);
    /* the exact reference: the tessellation-free modes' own test */
    assert_int_equal(d->intersector, MR_DMM_INTERSECT_WATERTIGHT);
    assert_int_equal(d->level, 3);
    assert_int_equal(src->mode, MR_DMM_INTERPOLATED); /* the job's own is left alone */
    assert_true(p.job.objects[0].color.z == 0.3f);
    assert_ptr_equal(p.job.objects[1].params, job->objects[1].params);
    assert_ptr_equal(p.job.objects[1].kind, job->objects[1].kind);
    const mr_displaced_params *dp = p.job.objects[2].params;
    assert_int_equal(dp->method, MR_DISPLACED_TESSELLATED);
    mr_reference_pass_clear(&p);

    pass_of(job, MR_REFERENCE_GROUND_TRUTH, &p);
    assert_int_equal(p.job.object_count, 3);
    assert_ptr_equal(p.job.objects[0].kind, mr_kind_triangles());
    assert_null(p.job.objects[0].params);
    assert_ptr_equal(p.job.objects[1].kind, job->objects[1].kind);
    dp = p.job.objects[2].params;
    assert_ptr_equal(p.job.objects[2].kind, &mr_kind_displaced);
    assert_int_equal(dp->method, MR_DISPLACED_TESSELLATED);
    assert_int_equal(dp->level, 0);
    mr_reference_pass_clear(&p);
    mr_job_free(job);

    /* displaced: level 0 for a texture, twice the range for a procedural
     * source; springmass: trilinear */
    job = parse("\"reference\":true,",
                "{\"asset\":\"m\",\"kind\":\"displaced\",\"displaced\":{\"texture\":\"tex\",\"level\":2}},"
                "{\"asset\":\"m\",\"kind\":\"displaced\",\"displaced\":{\"procedural\":{\"example\":"
                "\"tex\"},\"range\":32}},"
                "{\"asset\":\"m\",\"kind\":\"springmass\",\"springmass\":{\"mapping\":\"one_to_one\"}}");
    pass_of(job, MR_REFERENCE_GROUND_TRUTH, &p);
    assert_int_equal(((const mr_displaced_params *)p.job.objects[0].params)->level, 0);
    assert_int_equal(((const mr_displaced_params *)p.job.objects[1].params)->range, 64);
    assert_int_equal(((const mr_displaced_params *)p.job.objects[1].params)->method,
                     MR_DISPLACED_TESSELLATED);
    assert_int_equal(((const mr_springmass_params *)p.job.objects[2].params)->mapping,
                     MR_SPRINGMASS_TRILINEAR);
    mr_reference_pass_clear(&p);
    pass_of(job, MR_REFERENCE_TESSELLATED, &p);
    assert_int_equal(((const mr_displaced_params *)p.job.objects[0].params)->level, 2);
    assert_ptr_equal(p.job.objects[2].params, job->objects[2].params); /* itself */
    mr_reference_pass_clear(&p);
    mr_job_free(job);
}

static void test_svo_instances(void **state)
{
    (void)state;
    mr_job *job = parse("\"reference\":true,",
                        "{\"asset\":\"m\",\"kind\":\"svo\",\"transform\":{\"translation\":[0,0,-2]},"
                        "\"pose\":{\"clip\":0},\"svo\":{\"method\":\"emit\",\"instances\":["
                        "{\"transform\":{\"translation\":[1,0,0]}},"
                        "{\"transform\":{\"scale\":[2,2,2]},\"pose\":{\"clip\":1}}]}},"
                        "{\"asset\":\"m\",\"kind\":\"svo\",\"pose\":{\"clip\":0},"
                        "\"svo\":{\"method\":\"direct\"}}");
    mr_reference_pass p;
    bool present = true;
    mr_error err = {0};
    assert_int_equal(mr_reference_pass_init(job, MR_REFERENCE_TESSELLATED, &p, &present, &err), MR_OK);
    assert_false(present); /* voxels have no tessellation */
    pass_of(job, MR_REFERENCE_GROUND_TRUTH, &p);
    assert_int_equal(p.job.object_count, 3);
    for (size_t i = 0; i < 3; i++) {
        assert_ptr_equal(p.job.objects[i].kind, mr_kind_triangles());
        assert_int_equal(p.job.objects[i].pose_count, 1);
    }
    /* the instance's transform after the object's */
    mr_vec3 o = mr_mat4_point(&p.job.objects[0].transform, mr_v3(0, 0, 0));
    assert_true(o.x == 1 && o.z == -2);
    mr_vec3 x = mr_mat4_point(&p.job.objects[1].transform, mr_v3(1, 0, 0));
    assert_true(x.x == 2 && x.z == -2);
    /* the object's pose, or the instance's own */
    assert_ptr_equal(p.job.objects[0].poses, job->objects[0].poses);
    const mr_svo_params *s = job->objects[0].params;
    assert_ptr_equal(p.job.objects[1].poses, &s->instances[1].pose);
    mr_reference_pass_clear(&p);
    mr_job_free(job);

    /* rigid instances (the default method) ignore poses: the rest pose */
    job = parse("\"reference\":true,",
                "{\"asset\":\"m\",\"kind\":\"svo\",\"pose\":{\"clip\":0}}");
    pass_of(job, MR_REFERENCE_GROUND_TRUTH, &p);
    assert_int_equal(p.job.object_count, 1);
    assert_int_equal(p.job.objects[0].pose_count, 0);
    mr_reference_pass_clear(&p);
    mr_job_free(job);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_passes_per_kind),
        cmocka_unit_test(test_what_passes_draw),
        cmocka_unit_test(test_svo_instances),
    };
    return cmocka_run_group_tests(tests, NULL, NULL);
}
