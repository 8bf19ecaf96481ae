/*
 * test_schema.c - schemas/job.schema.json must not drift from the parser
 * (server/job_json.c, mr_job_parse()), which is the authority.
 *
 * The schema is checked by a real JSON Schema 2020-12 validator: ajv-cli
 * (ajv 8), which scripts/setup.sh installs into tests/schema/node_modules
 * from the pinned tests/schema/package-lock.json ($MR_AJV overrides the
 * path). It runs once, as `ajv validate --spec=draft2020` over every file
 * below, with strict types and tuples on, so a schema that ajv would only
 * warn about fails here.
 *
 * (1) Every examples/NAME.json and tests/data/NAME.json that the parser
 *     accepts must be valid under the schema.
 * (2) AGREE: small jobs, each with the verdict that both the parser and the
 *     schema must give (both accept or both reject).
 * (3) PARSER_ONLY: the parser's checks that a schema cannot express, each
 *     with its reason. The parser refuses these jobs and the schema lets
 *     them through; they are not counted as agreement. Should the schema
 *     learn to express one, its case fails here: move it to AGREE.
 *
 * Job text is written with single quotes, turned into double quotes here
 * (as in test_job.c). Each job goes to the parser in an exactly-sized heap
 * buffer without a NUL, and to ajv as a file of the same bytes.
 */
#include <setjmp.h>
#include <stdarg.h>
#include <stddef.h>
#include <stdint.h>
#include <cmocka.h>

#include <dirent.h>
#include <errno.h>
#include <fcntl.h>
#include <spawn.h>
#include <stdbool.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include "job_json.h"
#include "schema_gen.h"

extern char **environ;

typedef enum { ACCEPT, REJECT } verdict;

static const char *verdict_name(verdict v) { return v == ACCEPT ? "accept" : "reject"; }

typedef struct agree_case {
    const char *name;
    verdict expect; /* of both the parser and the schema */
    const char *json;
} agree_case;

typedef struct parser_only_case {
    const char *name;
    const char *why; /* why the schema cannot say it */
    const char *json; /* the parser rejects it, the schema accepts it */
} parser_only_case;

/* ------------------------------------------------------------------------ */
/* The jobs.                                                                */

#define ASSETS "'assets':{'m':{'path':'/a.gltf'}}"
#define KEY "{'t':0,'position':[0,0,5],'target':[0,0,0]}"
#define OBJECTS "'objects':[{'asset':'m'}]"
#define CAMERA "'camera':{'path':[" KEY "]}"
#define FRAMES "'frames':{'times':[0]}"
/* The minimal valid job, with extra root fields (each starting with ','). */
#define JOB(extra) "{" ASSETS "," OBJECTS "," CAMERA "," FRAMES extra "}"
#define WITH_ASSETS(a) "{'assets':" a "," OBJECTS "," CAMERA "," FRAMES "}"
#define WITH_OBJECT(o) "{" ASSETS ",'objects':[" o "]," CAMERA "," FRAMES "}"
#define WITH_CAMERA(c) "{" ASSETS "," OBJECTS ",'camera':" c "," FRAMES "}"
#define WITH_FRAMES(f) "{" ASSETS "," OBJECTS "," CAMERA ",'frames':" f "}"
#define WITH_KEYS(k) WITH_CAMERA("{'path':[" k "]}")
#define WITH_POSE(p) WITH_OBJECT("{'asset':'m','pose':" p "}")
#define WITH_XF(t) WITH_OBJECT("{'asset':'m','transform':" t "}")
#define WITH_DMM(d) WITH_OBJECT("{'asset':'m','kind':'dmm','dmm':" d "}")
#define WITH_SVO(s) WITH_OBJECT("{'asset':'m','kind':'svo','svo':" s "}")
#define WITH_DISP(d) WITH_OBJECT("{'asset':'m','kind':'displaced','displaced':" d "}")
#define WITH_LIGHTS(l) JOB(",'lights':" l)
#define WITH_OUTPUT(o) JOB(",'output':" o)
/* A 4x4 matrix whose last row is given. */
#define MATRIX(last) "{'matrix':[1,0,0,0, 0,1,0,0, 0,0,1,0, " last "]}"

#define S16 "abcdefghijklmnop"
#define S64 S16 S16 S16 S16
#define S256 S64 S64 S64 S64
/* U+00E9, two bytes in UTF-8. */
#define E1 "\xc3\xa9"
#define E8 E1 E1 E1 E1 E1 E1 E1 E1
#define E64 E8 E8 E8 E8 E8 E8 E8 E8
#define E200 E64 E64 E64 E8

static const agree_case AGREE[] = {
    /* The root. */
    {"minimal job", ACCEPT, JOB("")},
    {"root fields at their limits", ACCEPT,
     JOB(",'name':'x','priority':-1000,'max_retries':10,'ambient':[0,0,1000]")},
    {"name of 256 characters", ACCEPT, JOB(",'name':'" S256 "'")},
    {"root is an array", REJECT, "[]"},
    {"missing assets", REJECT, "{" OBJECTS "," CAMERA "," FRAMES "}"},
    {"missing objects", REJECT, "{" ASSETS "," CAMERA "," FRAMES "}"},
    {"missing camera", REJECT, "{" ASSETS "," OBJECTS "," FRAMES "}"},
    {"missing frames", REJECT, "{" ASSETS "," OBJECTS "," CAMERA "}"},
    {"unknown root field", REJECT, JOB(",'colour':[1,1,1]")},
    {"priority over 1000", REJECT, JOB(",'priority':1001")},
    {"priority not an integer", REJECT, JOB(",'priority':1.5")},
    {"max_retries as a string", REJECT, JOB(",'max_retries':'2'")},
    {"max_retries over 10", REJECT, JOB(",'max_retries':11")},
    {"name empty", REJECT, JOB(",'name':''")},
    {"name of 257 characters", REJECT, JOB(",'name':'" S256 "x'")},
    {"name with a control character", REJECT, JOB(",'name':'a\\u0001b'")},
    {"name with an escaped NUL", REJECT, JOB(",'name':'a\\u0000b'")},
    {"name null", REJECT, JOB(",'name':null")},
    {"ambient negative", REJECT, JOB(",'ambient':[-0.1,0,0]")},
    {"ambient overflowing to -inf (-1e999)", REJECT, JOB(",'ambient':[-1e999,0,0]")},
    /* Assets. */
    {"asset name of 64 characters", ACCEPT,
     WITH_ASSETS("{'m':{'path':'/a.gltf'},'" S64 "':{'path':'/b.gltf'}}")},
    {"asset by id", ACCEPT,
     WITH_ASSETS("{'m':{'id':'0123456789abcdef0123456789abcdef0123456789abcdef0123456789abcdef'}}")},
    {"asset refine at its limits", ACCEPT,
     WITH_ASSETS("{'m':{'path':'/a.gltf','refine':{'rounds':4,'amplitude':1e9,'frequency':1e9,"
                 "'octaves':8,'seed':4294967295}}}")},
    {"asset refine empty", ACCEPT, WITH_ASSETS("{'m':{'path':'/a.gltf','refine':{}}}")},
    {"no assets", REJECT, WITH_ASSETS("{}")},
    {"asset name with a space", REJECT, WITH_ASSETS("{'m':{'path':'/a.gltf'},'a b':{'path':'/b'}}")},
    {"asset name of 65 characters", REJECT,
     WITH_ASSETS("{'m':{'path':'/a.gltf'},'" S64 "x':{'path':'/b.gltf'}}")},
    {"asset with path and id", REJECT,
     WITH_ASSETS("{'m':{'path':'/a.gltf','id':'0123456789abcdef0123456789abcdef0123456789abcdef"
                 "0123456789abcdef'}}")},
    {"asset with neither path nor id", REJECT, WITH_ASSETS("{'m':{'refine':{}}}")},
    {"asset id in upper case", REJECT,
     WITH_ASSETS("{'m':{'id':'0123456789ABCDEF0123456789abcdef0123456789abcdef0123456789abcdef'}}")},
    {"asset id of 63 digits", REJECT,
     WITH_ASSETS("{'m':{'id':'0123456789abcdef0123456789abcdef0123456789abcdef0123456789abcde'}}")},
    {"asset path empty", REJECT, WITH_ASSETS("{'m':{'path':''}}")},
    {"asset unknown field", REJECT, WITH_ASSETS("{'m':{'path':'/a.gltf','url':'x'}}")},
    {"refine rounds 5", REJECT, WITH_ASSETS("{'m':{'path':'/a.gltf','refine':{'rounds':5}}}")},
    {"refine frequency 0", REJECT, WITH_ASSETS("{'m':{'path':'/a.gltf','refine':{'frequency':0}}}")},
    {"refine seed -1", REJECT, WITH_ASSETS("{'m':{'path':'/a.gltf','refine':{'seed':-1}}}")},
    {"refine amplitude negative", REJECT,
     WITH_ASSETS("{'m':{'path':'/a.gltf','refine':{'amplitude':-1}}}")},
    {"refine unknown field", REJECT, WITH_ASSETS("{'m':{'path':'/a.gltf','refine':{'level':1}}}")},
    /* Objects. */
    {"object with every mesh field", ACCEPT,
     WITH_OBJECT("{'name':'o','asset':'m','kind':'mesh','color':[1000,0,0.5],"
                 "'transform':{'translation':[1,2,3]},'pose':{'clip':0}}")},
    {"no objects", REJECT, "{" ASSETS ",'objects':[]," CAMERA "," FRAMES "}"},
    {"object without asset", REJECT, WITH_OBJECT("{'name':'o'}")},
    {"object asset not a string", REJECT, WITH_OBJECT("{'asset':5}")},
    {"object unknown field", REJECT, WITH_OBJECT("{'asset':'m','material':'x'}")},
    {"object kind not in the enum", REJECT, WITH_OBJECT("{'asset':'m','kind':'voxel'}")},
    {"object color over 1000", REJECT, WITH_OBJECT("{'asset':'m','color':[0,0,1001]}")},
    {"object color of 2 numbers", REJECT, WITH_OBJECT("{'asset':'m','color':[0,0]}")},
    {"object transform null", REJECT, WITH_OBJECT("{'asset':'m','transform':null}")},
    /* Transforms. */
    {"TRS with every field", ACCEPT,
     WITH_XF("{'translation':[-1e9,0,1e9],'rotation':[0,0.7071,0,0.7071],'scale':[2,-1,0.5]}")},
    {"TRS empty (identity)", ACCEPT, WITH_XF("{}")},
    {"rotation tiny but non-zero", ACCEPT, WITH_XF("{'rotation':[1e-300,0,0,0]}")},
    {"TRS and matrix together", REJECT, WITH_XF("{'translation':[0,0,0],'matrix':[1,0,0,0,0,1,0,0,0,0,1,0,0,0,0,1]}")},
    {"scale with a 0", REJECT, WITH_XF("{'scale':[1,0,1]}")},
    {"scale with a -0", REJECT, WITH_XF("{'scale':[-0.0,1,1]}")},
    {"scale underflowing to 0 (1e-400)", REJECT, WITH_XF("{'scale':[1e-400,1,1]}")},
    {"rotation all zero", REJECT, WITH_XF("{'rotation':[0,0,0,0]}")},
    {"rotation of 3 numbers", REJECT, WITH_XF("{'rotation':[0,0,1]}")},
    {"translation over 1e9", REJECT, WITH_XF("{'translation':[0,0,1e10]}")},
    {"translation overflowing to inf (1e999)", REJECT, WITH_XF("{'translation':[0,0,1e999]}")},
    {"transform unknown field", REJECT, WITH_XF("{'shear':[0,0,0]}")},
    {"matrix identity", ACCEPT, WITH_XF(MATRIX("0,0,0,1"))},
    {"matrix last row [0,0,0,1.0000001] (1e-6 tolerance)", ACCEPT, WITH_XF(MATRIX("0,0,0,1.0000001"))},
    {"matrix last row [1e-6,-1e-6,1e-6,1.000001] (at the tolerance)", ACCEPT,
     WITH_XF(MATRIX("1e-6,-1e-6,1e-6,1.000001"))},
    {"matrix last w 0.9999990000000001 (smallest within 1e-6)", ACCEPT,
     WITH_XF(MATRIX("0,0,0,0.9999990000000001"))},
    {"matrix last w 0.999999 (1e-6 + 3e-17 below 1)", REJECT, WITH_XF(MATRIX("0,0,0,0.999999"))},
    {"matrix last w 1.0000011", REJECT, WITH_XF(MATRIX("0,0,0,1.0000011"))},
    {"matrix last row x 1.1e-6", REJECT, WITH_XF(MATRIX("1.1e-6,0,0,1"))},
    {"matrix projective last row", REJECT, WITH_XF(MATRIX("0,0,0.5,1"))},
    {"matrix of 15 numbers", REJECT, WITH_XF("{'matrix':[1,0,0,0,0,1,0,0,0,0,1,0,0,0,0]}")},
    {"matrix entry over 1e9", REJECT, WITH_XF("{'matrix':[1,0,0,2e9,0,1,0,0,0,0,1,0,0,0,0,1]}")},
    /* Poses. */
    {"pose clip by name with speed, offset, loop", ACCEPT,
     WITH_POSE("{'clip':'walk','speed':-1e6,'offset':1e9,'loop':false}")},
    {"pose clip by index with time", ACCEPT, WITH_POSE("{'clip':2147483647,'time':-1e9}")},
    {"pose joints only", ACCEPT,
     WITH_POSE("{'joints':{'arm/l':{'rotation':[0,0,1,1]},'leg':" MATRIX("0,0,0,1") "}}")},
    {"pose array of one pose per frame", ACCEPT, WITH_POSE("[{'clip':0}]")},
    {"pose with neither clip nor joints", REJECT, WITH_POSE("{}")},
    {"pose time and speed", REJECT, WITH_POSE("{'clip':0,'time':1,'speed':2}")},
    {"pose time and offset", REJECT, WITH_POSE("{'clip':0,'time':1,'offset':2}")},
    {"pose time without clip", REJECT, WITH_POSE("{'joints':{'a':{}},'time':1}")},
    {"pose loop without clip", REJECT, WITH_POSE("{'joints':{'a':{}},'loop':true}")},
    {"pose clip index negative", REJECT, WITH_POSE("{'clip':-1}")},
    {"pose clip index over INT_MAX", REJECT, WITH_POSE("{'clip':2147483648}")},
    {"pose clip index fractional", REJECT, WITH_POSE("{'clip':1.5}")},
    {"pose clip name empty", REJECT, WITH_POSE("{'clip':''}")},
    {"pose speed over 1e6", REJECT, WITH_POSE("{'clip':0,'speed':1000001}")},
    {"pose joints empty", REJECT, WITH_POSE("{'joints':{}}")},
    {"pose joint name empty", REJECT, WITH_POSE("{'joints':{'':{}}}")},
    {"pose unknown field", REJECT, WITH_POSE("{'clip':0,'weight':1}")},
    {"pose array empty", REJECT, WITH_POSE("[]")},
    {"pose a string", REJECT, WITH_POSE("'walk'")},
    /* The dmm kind: every field, its enums and ranges, the alternatives. */
    {"dmm kind without a block", ACCEPT, WITH_OBJECT("{'asset':'m','kind':'dmm'}")},
    {"dmm block empty", ACCEPT, WITH_DMM("{}")},
    {"dmm every field", ACCEPT,
     WITH_DMM("{'level':5,'base_triangles':16777216,'mode':'tessellated',"
              "'deformation':'interpolated','normals':'matrix','levels':'adaptive'}")},
    {"dmm level 0, base_ratio 1, uniform, geometric", ACCEPT,
     WITH_DMM("{'level':0,'base_ratio':1,'levels':'uniform','normals':'geometric'}")},
    {"dmm mode base, deformation base", ACCEPT, WITH_DMM("{'mode':'base','deformation':'base'}")},
    {"dmm mode interpolated, deformation interpolated", ACCEPT,
     WITH_DMM("{'mode':'interpolated','deformation':'interpolated'}")},
    {"dmm mode interpolated alone", ACCEPT, WITH_DMM("{'mode':'interpolated'}")},
    {"dmm deformation interpolated alone (tessellated)", ACCEPT,
     WITH_DMM("{'deformation':'interpolated'}")},
    {"dmm level 6", REJECT, WITH_DMM("{'level':6}")},
    {"dmm level -1", REJECT, WITH_DMM("{'level':-1}")},
    {"dmm level 2.5", REJECT, WITH_DMM("{'level':2.5}")},
    {"dmm level as a string", REJECT, WITH_DMM("{'level':'3'}")},
    {"dmm base_ratio 0", REJECT, WITH_DMM("{'base_ratio':0}")},
    {"dmm base_ratio 1.5", REJECT, WITH_DMM("{'base_ratio':1.5}")},
    {"dmm base_triangles 0", REJECT, WITH_DMM("{'base_triangles':0}")},
    {"dmm base_triangles 16777217", REJECT, WITH_DMM("{'base_triangles':16777217}")},
    {"dmm base_triangles fractional", REJECT, WITH_DMM("{'base_triangles':10.5}")},
    {"dmm base_ratio and base_triangles", REJECT, WITH_DMM("{'base_ratio':0.5,'base_triangles':100}")},
    {"dmm mode not in the enum", REJECT, WITH_DMM("{'mode':'prism'}")},
    {"dmm mode base, deformation interpolated", REJECT,
     WITH_DMM("{'mode':'base','deformation':'interpolated'}")},
    {"dmm mode interpolated, deformation base", REJECT,
     WITH_DMM("{'mode':'interpolated','deformation':'base'}")},
    {"dmm deformation not in the enum", REJECT, WITH_DMM("{'deformation':'skinned'}")},
    {"dmm normals not in the enum", REJECT, WITH_DMM("{'normals':'phong'}")},
    {"dmm levels not in the enum", REJECT, WITH_DMM("{'levels':'mixed'}")},
    {"dmm unknown field", REJECT, WITH_DMM("{'lod':1}")},
    {"dmm block an array", REJECT, WITH_DMM("[]")},
    {"dmm block on a mesh object", REJECT, WITH_OBJECT("{'asset':'m','kind':'mesh','dmm':{}}")},
    {"dmm block without kind", REJECT, WITH_OBJECT("{'asset':'m','dmm':{}}")},
    {"dmm block on an svo object", REJECT, WITH_OBJECT("{'asset':'m','kind':'svo','dmm':{}}")},
    /* The svo kind. */
    {"svo kind without a block", ACCEPT, WITH_OBJECT("{'asset':'m','kind':'svo'}")},
    {"svo every field", ACCEPT,
     WITH_SVO("{'depth':12,'voxelize':'surface','method':'emit','delta':1e6,'cull':false,"
              "'skeleton':{'omega':0.5},'instances':[{'transform':{'translation':[1,0,0]},"
              "'pose':{'clip':'run'}},{}]}")},
    {"svo methods rigid, skeleton true", ACCEPT, WITH_SVO("{'method':'rigid','skeleton':true}")},
    {"svo method direct, skeleton {}", ACCEPT, WITH_SVO("{'method':'direct','skeleton':{}}")},
    {"svo method resize, skeleton false", ACCEPT, WITH_SVO("{'method':'resize','skeleton':false}")},
    {"svo depth 1, delta tiny", ACCEPT, WITH_SVO("{'depth':1,'delta':1e-30}")},
    {"svo solid at depth 10", ACCEPT, WITH_SVO("{'voxelize':'solid','depth':10}")},
    {"svo solid at the default depth", ACCEPT, WITH_SVO("{'voxelize':'solid'}")},
    {"svo depth 11 surface", ACCEPT, WITH_SVO("{'voxelize':'surface','depth':11}")},
    {"svo depth 0", REJECT, WITH_SVO("{'depth':0}")},
    {"svo depth 13", REJECT, WITH_SVO("{'depth':13}")},
    {"svo solid at depth 11", REJECT, WITH_SVO("{'voxelize':'solid','depth':11}")},
    {"svo voxelize not in the enum", REJECT, WITH_SVO("{'voxelize':'volume'}")},
    {"svo method not in the enum", REJECT, WITH_SVO("{'method':'skinned'}")},
    {"svo delta 0", REJECT, WITH_SVO("{'delta':0}")},
    {"svo delta over 1e6", REJECT, WITH_SVO("{'delta':1000001}")},
    {"svo cull a string", REJECT, WITH_SVO("{'cull':'yes'}")},
    {"svo skeleton omega 0", REJECT, WITH_SVO("{'skeleton':{'omega':0}}")},
    {"svo skeleton omega 0.6", REJECT, WITH_SVO("{'skeleton':{'omega':0.6}}")},
    {"svo skeleton unknown field", REJECT, WITH_SVO("{'skeleton':{'sigma':1}}")},
    {"svo skeleton a number", REJECT, WITH_SVO("{'skeleton':1}")},
    {"svo instances empty", REJECT, WITH_SVO("{'instances':[]}")},
    {"svo instance unknown field", REJECT, WITH_SVO("{'instances':[{'color':[1,1,1]}]}")},
    {"svo instance pose an array", REJECT, WITH_SVO("{'instances':[{'pose':[{'clip':0}]}]}")},
    {"svo instance transform with a 0 scale", REJECT,
     WITH_SVO("{'instances':[{'transform':{'scale':[0,1,1]}}]}")},
    {"svo unknown field", REJECT, WITH_SVO("{'radius':1}")},
    /* The displaced kind: a height source (exactly one), its ranges, the
     * fields that go with one source or one method only. */
    {"displaced with a texture", ACCEPT, WITH_DISP("{'texture':'m'}")},
    {"displaced texture, every field at its limits", ACCEPT,
     WITH_DISP("{'texture':'m','scale':-1000000,'offset':1000000,'level':16,'method':'raymarch',"
               "'steps':100000,'local':'bilinear'}")},
    {"displaced procedural, every field at its limits", ACCEPT,
     WITH_DISP("{'procedural':{'example':'m','offset':[-1000000,1000000],'scale':1000000,"
               "'triangle_size':16,'seed':4294967295},'range':4096,'method':'tessellated'}")},
    {"displaced procedural with its example only", ACCEPT,
     WITH_DISP("{'procedural':{'example':'m'},'range':1}")},
    {"displaced block empty", REJECT, WITH_DISP("{}")},
    {"displaced texture and procedural", REJECT,
     WITH_DISP("{'texture':'m','procedural':{'example':'m'}}")},
    {"displaced texture not a string", REJECT, WITH_DISP("{'texture':1}")},
    {"displaced level 17", REJECT, WITH_DISP("{'texture':'m','level':17}")},
    {"displaced level with procedural", REJECT,
     WITH_DISP("{'procedural':{'example':'m'},'level':1}")},
    {"displaced range with a texture", REJECT, WITH_DISP("{'texture':'m','range':8}")},
    {"displaced range 24 (not a power of two)", REJECT,
     WITH_DISP("{'procedural':{'example':'m'},'range':24}")},
    {"displaced range 8192", REJECT, WITH_DISP("{'procedural':{'example':'m'},'range':8192}")},
    {"displaced steps without raymarch", REJECT, WITH_DISP("{'texture':'m','steps':64}")},
    {"displaced steps 0", REJECT, WITH_DISP("{'texture':'m','method':'raymarch','steps':0}")},
    {"displaced method not in the enum", REJECT, WITH_DISP("{'texture':'m','method':'rmip'}")},
    {"displaced local not in the enum", REJECT, WITH_DISP("{'texture':'m','local':'boxes'}")},
    {"displaced procedural without example", REJECT, WITH_DISP("{'procedural':{'seed':1}}")},
    {"displaced procedural offset of 3 numbers", REJECT,
     WITH_DISP("{'procedural':{'example':'m','offset':[0,0,0]}}")},
    {"displaced procedural scale 0", REJECT, WITH_DISP("{'procedural':{'example':'m','scale':0}}")},
    {"displaced procedural triangle_size 0", REJECT,
     WITH_DISP("{'procedural':{'example':'m','triangle_size':0}}")},
    {"displaced unknown field", REJECT, WITH_DISP("{'texture':'m','heights':'m'}")},
    {"displaced block on a mesh object", REJECT,
     WITH_OBJECT("{'asset':'m','kind':'mesh','displaced':{'texture':'m'}}")},
    {"svo block on a dmm object", REJECT, WITH_OBJECT("{'asset':'m','kind':'dmm','svo':{}}")},
    {"svo block without kind", REJECT, WITH_OBJECT("{'asset':'m','svo':{}}")},
    /* Lights and background. */
    {"no lights", ACCEPT, WITH_LIGHTS("[]")},
    {"light with every field", ACCEPT,
     WITH_LIGHTS("[{'direction':[3.4e38,-1,0],'color':[1000,0,1],'intensity':1000}]")},
    {"light direction tiny but non-zero", ACCEPT, WITH_LIGHTS("[{'direction':[0,0,1e-300]}]")},
    {"light without direction", REJECT, WITH_LIGHTS("[{'intensity':1}]")},
    {"light direction zero", REJECT, WITH_LIGHTS("[{'direction':[0,0,0]}]")},
    {"light direction beyond float (3.5e38)", REJECT, WITH_LIGHTS("[{'direction':[3.5e38,0,0]}]")},
    {"light direction overflowing to inf (1e999)", REJECT,
     WITH_LIGHTS("[{'direction':[1e999,0,0]}]")},
    {"light intensity over 1000", REJECT, WITH_LIGHTS("[{'direction':[0,-1,0],'intensity':1001}]")},
    {"light unknown field", REJECT, WITH_LIGHTS("[{'direction':[0,-1,0],'kind':'sun'}]")},
    {"lights not an array", REJECT, WITH_LIGHTS("{'direction':[0,-1,0]}")},
    {"background with every field", ACCEPT, JOB(",'background':{'color':[0,0,0],'alpha':0}")},
    {"background alpha 1.5", REJECT, JOB(",'background':{'alpha':1.5}")},
    {"background unknown field", REJECT, JOB(",'background':{'colour':[0,0,0]}")},
    /* Camera. */
    {"camera path with every field", ACCEPT,
     WITH_CAMERA("{'interpolation':'linear','up':[0,0,1],'yfov':179.9,'path':["
                 "{'t':-1e9,'position':[0,0,5],'rotation':[0,0,0,1],'yfov':0.001},"
                 "{'t':1,'position':[0,0,5],'target':[0,0,0]},"
                 "{'t':1e9,'position':[1e9,0,5],'target':[0,0,-1e9]}]}")},
    {"camera node", ACCEPT, WITH_CAMERA("{'node':{'asset':'m','name':'cam'}}")},
    {"camera key with target and rotation", REJECT,
     WITH_KEYS("{'t':0,'position':[0,0,5],'target':[0,0,0],'rotation':[0,0,0,1]}")},
    {"camera key with neither target nor rotation", REJECT, WITH_KEYS("{'t':0,'position':[0,0,5]}")},
    {"camera key without t", REJECT, WITH_KEYS("{'position':[0,0,5],'target':[0,0,0]}")},
    {"camera key without position", REJECT, WITH_KEYS("{'t':0,'target':[0,0,0]}")},
    {"camera key unknown field", REJECT,
     WITH_KEYS("{'t':0,'position':[0,0,5],'target':[0,0,0],'roll':0}")},
    /* The parser once checked only the first key's t against the time cap. */
    {"camera later key t over 1e9", REJECT, WITH_KEYS(KEY ",{'t':2e9,'position':[0,0,5],'target':[0,0,0]}")},
    {"camera key t overflowing to inf (1e999)", REJECT,
     WITH_KEYS("{'t':1e999,'position':[0,0,5],'target':[0,0,0]}")},
    {"camera yfov 180", REJECT, WITH_CAMERA("{'yfov':180,'path':[" KEY "]}")},
    {"camera key yfov 0", REJECT, WITH_KEYS("{'t':0,'position':[0,0,5],'target':[0,0,0],'yfov':0}")},
    {"camera interpolation not in the enum", REJECT,
     WITH_CAMERA("{'interpolation':'cubic','path':[" KEY "]}")},
    {"camera up zero", REJECT, WITH_CAMERA("{'up':[0,0,0],'path':[" KEY "]}")},
    {"camera path empty", REJECT, WITH_CAMERA("{'path':[]}")},
    {"camera empty", REJECT, WITH_CAMERA("{}")},
    {"camera path and node", REJECT,
     WITH_CAMERA("{'path':[" KEY "],'node':{'asset':'m','name':'cam'}}")},
    {"camera node with yfov", REJECT, WITH_CAMERA("{'yfov':40,'node':{'asset':'m','name':'cam'}}")},
    {"camera node without name", REJECT, WITH_CAMERA("{'node':{'asset':'m'}}")},
    {"camera node unknown field", REJECT, WITH_CAMERA("{'node':{'asset':'m','name':'c','fov':1}}")},
    /* Frames. */
    {"frames range with every field", ACCEPT, WITH_FRAMES("{'fps':1000,'start':-1,'end':-1}")},
    {"frames range end only", ACCEPT, WITH_FRAMES("{'end':1}")},
    {"frames times unordered, at the caps", ACCEPT, WITH_FRAMES("{'fps':0.5,'times':[1e9,-1e9,0]}")},
    {"frames fps 0", REJECT, WITH_FRAMES("{'fps':0,'end':1}")},
    {"frames fps 1001", REJECT, WITH_FRAMES("{'fps':1001,'end':1}")},
    {"frames end and times", REJECT, WITH_FRAMES("{'end':1,'times':[0]}")},
    {"frames start and times", REJECT, WITH_FRAMES("{'start':0,'times':[0]}")},
    {"frames neither end nor times", REJECT, WITH_FRAMES("{'fps':24}")},
    {"frames start without end", REJECT, WITH_FRAMES("{'start':0}")},
    {"frames times empty", REJECT, WITH_FRAMES("{'times':[]}")},
    {"frames times as strings", REJECT, WITH_FRAMES("{'times':['0']}")},
    {"frames times overflowing to inf (1e999)", REJECT, WITH_FRAMES("{'times':[1e999]}")},
    {"frames end over 1e9", REJECT, WITH_FRAMES("{'end':1e10}")},
    {"frames unknown field", REJECT, WITH_FRAMES("{'end':1,'step':1}")},
    /* Output. */
    {"output with every field", ACCEPT,
     WITH_OUTPUT("{'width':8192,'height':2048,'samples':1024,'shadows':false,'seed':4294967295,"
                 "'compression':'piz','zip_level':9,'aovs':['id','rgba'],"
                 "'normals':'half'}")},
    {"output integers written as 2.0 and 1e2", ACCEPT, WITH_OUTPUT("{'width':2.0,'height':1e2}")},
    {"output width 0", REJECT, WITH_OUTPUT("{'width':0}")},
    {"output width 8193", REJECT, WITH_OUTPUT("{'width':8193}")},
    {"output width overflowing to inf (1e999)", REJECT, WITH_OUTPUT("{'width':1e999}")},
    {"output height fractional", REJECT, WITH_OUTPUT("{'height':1.5}")},
    {"output samples 1025", REJECT, WITH_OUTPUT("{'samples':1025}")},
    {"output seed 2^32", REJECT, WITH_OUTPUT("{'seed':4294967296}")},
    {"output compression in upper case", REJECT, WITH_OUTPUT("{'compression':'ZIP'}")},
    {"output zip_level 0", REJECT, WITH_OUTPUT("{'zip_level':0}")},
    {"output shadows a number", REJECT, WITH_OUTPUT("{'shadows':1}")},
    {"output unknown field", REJECT, WITH_OUTPUT("{'format':'exr'}")},
    {"output aovs, every pass", ACCEPT,
     WITH_OUTPUT("{'aovs':['rgba','z','n','p','id','cryptomatte','t']}")},
    {"output aovs, one pass", ACCEPT, WITH_OUTPUT("{'aovs':['z']}")},
    {"output aovs empty", REJECT, WITH_OUTPUT("{'aovs':[]}")},
    {"output aovs with a pass twice", REJECT, WITH_OUTPUT("{'aovs':['z','rgba','z']}")},
    {"output aovs unknown pass", REJECT, WITH_OUTPUT("{'aovs':['rgb']}")},
    {"output aovs pass in upper case", REJECT, WITH_OUTPUT("{'aovs':['Z']}")},
    {"output aovs a string", REJECT, WITH_OUTPUT("{'aovs':'rgba'}")},
    {"output aovs with a number", REJECT, WITH_OUTPUT("{'aovs':['rgba',1]}")},
    {"output normals half", ACCEPT, WITH_OUTPUT("{'normals':'half'}")},
    {"output normals float", ACCEPT, WITH_OUTPUT("{'normals':'float'}")},
    {"output normals double", REJECT, WITH_OUTPUT("{'normals':'double'}")},
    {"output normals a boolean", REJECT, WITH_OUTPUT("{'normals':true}")},
    /* Reference passes (issue 16). */
    {"reference on the job", ACCEPT, JOB(",'reference':true")},
    {"reference false", ACCEPT, JOB(",'reference':false")},
    {"reference yes", REJECT, JOB(",'reference':'yes'")},
    {"reference on an object", ACCEPT, WITH_DMM("{'mode':'base'},'reference':true")},
    {"reference on an object a number", REJECT, WITH_OBJECT("{'asset':'m','reference':1}")},
    {"reference with every compared pass", ACCEPT,
     JOB(",'reference':true,'output':{'aovs':['id','n','z','rgba','p']}")},
};

static const parser_only_case PARSER_ONLY[] = {
    {"camera key times not increasing",
     "a relation between array items (each t greater than the previous key's)",
     WITH_KEYS(KEY "," KEY)},
    {"camera key target equal to position",
     "a relation between two fields of one key, compared as stored floats",
     WITH_KEYS("{'t':0,'position':[1,2,3],'target':[1,2,3]}")},
    {"frames end before start", "a relation between two fields (end >= start)",
     WITH_FRAMES("{'start':1,'end':0.5}")},
    {"frames end before the default start 0", "end >= start, start defaulting to 0",
     WITH_FRAMES("{'end':-1}")},
    {"frames range of more than 100000 frames",
     "the count floor((end - start) * fps + 1e-9) + 1 is computed from three fields",
     WITH_FRAMES("{'fps':1000,'start':0,'end':1000}")},
    {"pose array length not the frame count",
     "the length must equal the number of frames, computed from another section",
     WITH_POSE("[{'clip':0},{'clip':1}]")},
    {"width * height over 16777216", "a product of two fields",
     WITH_OUTPUT("{'width':8192,'height':8192}")},
    {"matrix singular", "invertibility (|det| > 1e-12 * max^3) is arithmetic on 9 entries",
     WITH_XF("{'matrix':[1,0,0,0, 0,1,0,0, 0,0,0,0, 0,0,0,1]}")},
    {"TRS numerically singular", "invertibility of the composed matrix",
     WITH_XF("{'scale':[1e9,1e-9,1]}")},
    {"object asset names no asset", "a reference to a key of another object (\"assets\")",
     WITH_OBJECT("{'asset':'ghost'}")},
    {"displaced texture names no asset", "a reference to a key of \"assets\"",
     WITH_DISP("{'texture':'ghost'}")},
    {"displaced kind without its block", "the kind's rules (a height source) hold when its block "
     "is absent; the schema checks a block only where there is one",
     WITH_OBJECT("{'asset':'m','kind':'displaced'}")},
    {"displaced procedural true", "the flag object's boolean form is generic; this kind's needs "
     "an example", WITH_DISP("{'procedural':true}")},
    {"camera node asset names no asset", "a reference to a key of \"assets\"",
     WITH_CAMERA("{'node':{'asset':'ghost','name':'cam'}}")},
    {"duplicate key", "a validator sees the parsed value, where the last duplicate wins",
     WITH_OUTPUT("{'width':16,'width':32}")},
    {"name of 200 two-byte characters (400 bytes)",
     "the caps count UTF-8 bytes, maxLength counts characters", JOB(",'name':'" E200 "'")},
    {"name with an invalid UTF-8 byte",
     "a validator sees decoded text (the byte became U+FFFD)", JOB(",'name':'a\xff'")},
    {"name with a lone surrogate escape",
     "RFC 8259 allows it syntactically; a validator sees a string, cJSON refuses it",
     JOB(",'name':'a\\udc00'")},
    {"refine frequency 1e-50", "positive as a double, 0 as the 32-bit float the job stores",
     WITH_ASSETS("{'m':{'path':'/a.gltf','refine':{'frequency':1e-50}}}")},
    {"svo delta 1e-300", "in (0, 1e6] as a double, 0 as the 32-bit float the kind stores",
     WITH_OBJECT("{'asset':'m','kind':'svo','svo':{'delta':1e-300}}")},
    {"springmass dt needing more than 1000 substeps",
     "the stability bound is arithmetic on dt, mass and both stiffnesses",
     WITH_OBJECT("{'asset':'m','kind':'springmass','springmass':{'dt':0.01,'stiffness':1e9}}")},
    {"springmass steps of a frame over 100000", "a product of steps_per_frame and the substeps",
     WITH_OBJECT("{'asset':'m','kind':'springmass','springmass':{'steps_per_frame':100000,'stiffness':1e6}}")},
    {"springmass pin path keys not increasing", "a relation between array items",
     WITH_OBJECT("{'asset':'m','kind':'springmass','springmass':{'pins':[{'path':[{'t':1},{'t':0.5}]}]}}")},
    {"springmass pin box upside down", "a relation between two fields (box_max >= box_min)",
     WITH_OBJECT("{'asset':'m','kind':'springmass','springmass':{'pins':[{'box_min':[0,0,0],'box_max':[1,-1,1]}]}}")},
    {"reference without the passes it compares",
     "a relation between the job's and its objects' reference and output.aovs",
     JOB(",'reference':true,'output':{'aovs':['rgba','z']}")},
    {"reference with no object that has one",
     "which objects have references is each kind's code (kinds/kind.h reference)",
     WITH_SVO("{'skeleton':true},'reference':true")},
    {"springmass object with a pose", "which kinds take a pose is each kind's code "
     "(kinds/kind.h takes_no_pose)",
     WITH_OBJECT("{'asset':'m','kind':'springmass','pose':{'clip':0}}")},
    {"springmass force ending before it starts", "a relation between two fields (end > start)",
     WITH_OBJECT("{'asset':'m','kind':'springmass','springmass':{'forces':[{'start':2,'end':1}]}}")},
};

/* ------------------------------------------------------------------------ */
/* ajv, run once over every file.                                           */

typedef struct ajv_result {
    char *path;
    int verdict; /* -1 none seen, else ACCEPT or REJECT */
    char *errors;
} ajv_result;

typedef struct state {
    char dir[256]; /* temporary directory of the table's job files */
    char *schema;
    char *ajv;
    char *log; /* everything ajv printed */
    int ajv_status;
    ajv_result *files;
    size_t file_count, file_cap;
    size_t agree_first, parser_only_first, corpus_first;
} state;

static state S;

static char *xstrdup(const char *s)
{
    char *d = strdup(s);
    assert_non_null(d);
    return d;
}

static char *xprintf(const char *fmt, ...) __attribute__((format(printf, 1, 2)));
static char *xprintf(const char *fmt, ...)
{
    va_list ap;
    va_start(ap, fmt);
    int n = vsnprintf(NULL, 0, fmt, ap);
    va_end(ap);
    assert_true(n >= 0);
    char *out = malloc((size_t)n + 1);
    assert_non_null(out);
    va_start(ap, fmt);
    vsnprintf(out, (size_t)n + 1, fmt, ap);
    va_end(ap);
    return out;
}

static size_t add_file(const char *path)
{
    if (S.file_count == S.file_cap) {
        S.file_cap = S.file_cap ? 2 * S.file_cap : 64;
        S.files = realloc(S.files, S.file_cap * sizeof *S.files);
        assert_non_null(S.files);
    }
    S.files[S.file_count] = (ajv_result){xstrdup(path), -1, NULL};
    return S.file_count++;
}

/* The job text with single quotes made double, exactly sized, no NUL. */
static char *job_bytes(const char *quoted, size_t *len)
{
    size_t n = strlen(quoted);
    char *d = malloc(n ? n : 1);
    assert_non_null(d);
    for (size_t i = 0; i < n; i++)
        d[i] = quoted[i] == '\'' ? '"' : quoted[i];
    *len = n;
    return d;
}

static void write_file(const char *path, const char *bytes, size_t n)
{
    FILE *f = fopen(path, "wb");
    assert_non_null(f);
    assert_int_equal(fwrite(bytes, 1, n, f), n);
    assert_int_equal(fclose(f), 0);
}

static char *read_file(const char *path, size_t *len)
{
    FILE *f = fopen(path, "rb");
    if (!f)
        return NULL;
    size_t cap = 4096, n = 0;
    char *buf = malloc(cap);
    assert_non_null(buf);
    for (;;) {
        size_t got = fread(buf + n, 1, cap - n, f);
        n += got;
        if (n < cap)
            break;
        cap *= 2;
        buf = realloc(buf, cap);
        assert_non_null(buf);
    }
    fclose(f);
    *len = n;
    return buf;
}

static void write_case(const char *prefix, size_t i, const char *quoted)
{
    size_t n;
    char *bytes = job_bytes(quoted, &n);
    char *path = xprintf("%s/%s%03zu.json", S.dir, prefix, i);
    write_file(path, bytes, n);
    add_file(path);
    free(path);
    free(bytes);
}

static int cmp_str(const void *a, const void *b)
{
    return strcmp(*(char *const *)a, *(char *const *)b);
}

/* The *.json files of root/sub, sorted, added to the file list. */
static void add_corpus(const char *root, const char *sub)
{
    char *dir = xprintf("%s/%s", root, sub);
    DIR *d = opendir(dir);
    char **names = NULL;
    size_t n = 0;
    struct dirent *e;
    if (!d)
        fail_msg("cannot open %s: %s", dir, strerror(errno));
    while ((e = readdir(d)) != NULL) {
        size_t l = strlen(e->d_name);
        if (l < 6 || strcmp(e->d_name + l - 5, ".json") != 0)
            continue;
        names = realloc(names, (n + 1) * sizeof *names);
        assert_non_null(names);
        names[n++] = xprintf("%s/%s", dir, e->d_name);
    }
    closedir(d);
    qsort(names, n, sizeof *names, cmp_str);
    for (size_t i = 0; i < n; i++) {
        add_file(names[i]);
        free(names[i]);
    }
    free(names);
    free(dir);
}

/* Runs argv with stdout and stderr into log_path; returns the exit status
 * (or -1 if it could not run or was killed). */
static int run(char *const argv[], const char *log_path)
{
    posix_spawn_file_actions_t fa;
    pid_t pid;
    int status = 0;
    assert_int_equal(posix_spawn_file_actions_init(&fa), 0);
    assert_int_equal(posix_spawn_file_actions_addopen(&fa, 1, log_path,
                                                      O_WRONLY | O_CREAT | O_TRUNC, 0644), 0);
    assert_int_equal(posix_spawn_file_actions_adddup2(&fa, 1, 2), 0);
    assert_int_equal(posix_spawn_file_actions_addopen(&fa, 0, "/dev/null", O_RDONLY, 0), 0);
    int rc = posix_spawn(&pid, argv[0], &fa, NULL, argv, environ);
    posix_spawn_file_actions_destroy(&fa);
    if (rc != 0)
        return -1;
    while (waitpid(pid, &status, 0) < 0)
        if (errno != EINTR)
            return -1;
    return WIFEXITED(status) ? WEXITSTATUS(status) : -1;
}

/* ajv prints "<path> valid" (stdout) or "<path> invalid" and then one line
 * of errors (stderr, --errors=line) for each data file. */
static void read_verdicts(void)
{
    char *line = S.log, *next;
    ajv_result *last_invalid = NULL;
    for (; line && *line; line = next) {
        next = strchr(line, '\n');
        if (next)
            *next++ = '\0';
        bool matched = false;
        for (size_t i = 0; i < S.file_count && !matched; i++) {
            size_t pl = strlen(S.files[i].path);
            if (strncmp(line, S.files[i].path, pl) != 0)
                continue;
            if (strcmp(line + pl, " valid") == 0) {
                S.files[i].verdict = ACCEPT;
                matched = true;
                last_invalid = NULL;
            } else if (strcmp(line + pl, " invalid") == 0) {
                S.files[i].verdict = REJECT;
                matched = true;
                last_invalid = &S.files[i];
            }
        }
        if (!matched && last_invalid && !last_invalid->errors && line[0] == '[')
            last_invalid->errors = xstrdup(line);
        if (next)
            next[-1] = '\n';
    }
}

static int setup(void **unused)
{
    (void)unused;
    const char *root = getenv("MR_SOURCE_DIR");
    const char *tmp = getenv("TMPDIR");
    const char *ajv = getenv("MR_AJV");
    if (!root || !*root)
        root = ".";
    snprintf(S.dir, sizeof S.dir, "%s/mr-schema-XXXXXX", tmp && *tmp ? tmp : "/tmp");
    if (!mkdtemp(S.dir)) {
        fprintf(stderr, "mkdtemp %s: %s\n", S.dir, strerror(errno));
        return -1;
    }
    S.schema = xprintf("%s/schemas/job.schema.json", root);
    S.ajv = ajv && *ajv ? xstrdup(ajv) : xprintf("%s/tests/schema/node_modules/.bin/ajv", root);

    S.agree_first = S.file_count;
    for (size_t i = 0; i < sizeof AGREE / sizeof AGREE[0]; i++)
        write_case("agree", i, AGREE[i].json);
    S.parser_only_first = S.file_count;
    for (size_t i = 0; i < sizeof PARSER_ONLY / sizeof PARSER_ONLY[0]; i++)
        write_case("parser-only", i, PARSER_ONLY[i].json);
    S.corpus_first = S.file_count;
    add_corpus(root, "examples");
    add_corpus(root, "tests/data");

    if (access(S.ajv, X_OK) != 0) {
        S.ajv_status = -2;
        return 0;
    }
    /* ajv validate --spec=draft2020 --strict-types=true --strict-tuples=true
     *   -s SCHEMA --errors=line -d FILE ... */
    size_t argc = 0, cap = 8 + 2 * S.file_count + 1; /* and the NULL */
    char **argv = calloc(cap, sizeof *argv);
    assert_non_null(argv);
    argv[argc++] = S.ajv;
    argv[argc++] = "validate";
    argv[argc++] = "--spec=draft2020";
    argv[argc++] = "--strict-types=true";
    argv[argc++] = "--strict-tuples=true";
    argv[argc++] = "--errors=line";
    argv[argc++] = "-s";
    argv[argc++] = S.schema;
    for (size_t i = 0; i < S.file_count; i++) {
        argv[argc++] = "-d";
        argv[argc++] = S.files[i].path;
    }
    assert_true(argc < cap);
    argv[argc] = NULL;
    char *log_path = xprintf("%s/ajv.log", S.dir);
    S.ajv_status = run(argv, log_path);
    free(argv);
    size_t n = 0;
    S.log = read_file(log_path, &n);
    if (S.log) {
        S.log = realloc(S.log, n + 1);
        assert_non_null(S.log);
        S.log[n] = '\0';
    }
    unlink(log_path);
    free(log_path);
    read_verdicts();
    return 0;
}

static int teardown(void **unused)
{
    (void)unused;
    for (size_t i = 0; i < S.file_count; i++) {
        if (i < S.corpus_first)
            unlink(S.files[i].path);
        free(S.files[i].path);
        free(S.files[i].errors);
    }
    if (S.dir[0])
        rmdir(S.dir);
    free(S.files);
    free(S.schema);
    free(S.ajv);
    free(S.log);
    return 0;
}

/* ------------------------------------------------------------------------ */
/* Verdicts.                                                                */

static verdict parser_verdict(const char *bytes, size_t n, mr_job_error *err)
{
    char *buf = malloc(n ? n : 1);
    mr_job *job = NULL;
    assert_non_null(buf);
    memcpy(buf, bytes, n);
    int rc = mr_job_parse(buf, n, &job, err);
    free(buf);
    if (rc == MR_OK) {
        assert_non_null(job);
        mr_job_free(job);
        return ACCEPT;
    }
    assert_null(job);
    return REJECT;
}

static verdict parser_verdict_quoted(const char *quoted, mr_job_error *err)
{
    size_t n;
    char *bytes = job_bytes(quoted, &n);
    verdict v = parser_verdict(bytes, n, err);
    free(bytes);
    return v;
}

static const char *schema_why(const ajv_result *r)
{
    return r->errors ? r->errors : "";
}

/* ajv ran, compiled the schema (strictly) and judged every file. */
/* The committed schema is what `make schema` makes of it: its kind blocks
 * are those of the parameter tables the parser reads. */
static void test_schema_current(void **unused)
{
    (void)unused;
    FILE *f = fopen(S.schema, "rb");
    assert_non_null(f);
    static char text[1 << 20];
    size_t n = fread(text, 1, sizeof text - 1, f);
    fclose(f);
    assert_true(n > 0 && n < sizeof text - 1);
    text[n] = '\0';
    cJSON *doc = cJSON_Parse(text);
    assert_non_null(doc);
    mr_error err = {0};
    assert_int_equal(mr_schema_update(doc, &err), MR_OK);
    char *fresh = mr_schema_print(doc);
    assert_non_null(fresh);
    if (strcmp(fresh, text) != 0)
        fail_msg("schemas/job.schema.json is stale: run `make schema` (its kind blocks differ "
                 "from the parameter tables)");
    free(fresh);
    cJSON_Delete(doc);
}

static void test_ajv_ran(void **unused)
{
    (void)unused;
    if (S.ajv_status == -2)
        fail_msg("no ajv at %s: run scripts/setup.sh (make test does), or set MR_AJV", S.ajv);
    if (S.ajv_status != 0 && S.ajv_status != 1)
        fail_msg("ajv failed (status %d):\n%s", S.ajv_status, S.log ? S.log : "(no output)");
    size_t missing = 0, judged = 0;
    for (size_t i = 0; i < S.file_count; i++)
        judged += S.files[i].verdict >= 0;
    if (judged == 0)
        fail_msg("ajv judged no file (status %d):\n%s", S.ajv_status, S.log ? S.log : "");
    for (size_t i = 0; i < S.file_count; i++)
        if (S.files[i].verdict < 0) {
            print_error("ajv gave no verdict on %s\n", S.files[i].path);
            missing++;
        }
    if (missing)
        fail_msg("%zu files without a verdict; ajv said:\n%s", missing, S.log ? S.log : "");
    if (S.log && strstr(S.log, "strict mode"))
        fail_msg("ajv warned about the schema:\n%s", S.log);
}

static void need_ajv(void)
{
    if (S.ajv_status != 0 && S.ajv_status != 1)
        fail_msg("ajv did not run (see test_ajv_ran)");
}

/* (1) Every example and test job the parser accepts is valid. */
static void test_examples_and_data(void **unused)
{
    (void)unused;
    need_ajv();
    size_t bad = 0, accepted = 0;
    for (size_t i = S.corpus_first; i < S.file_count; i++) {
        const ajv_result *r = &S.files[i];
        size_t n = 0;
        char *bytes = read_file(r->path, &n);
        mr_job_error err;
        assert_non_null(bytes);
        verdict p = parser_verdict(bytes, n, &err);
        free(bytes);
        print_message("%-40s parser %s, schema %s\n", strrchr(r->path, '/') + 1,
                      verdict_name(p), r->verdict < 0 ? "?" : verdict_name((verdict)r->verdict));
        if (p == ACCEPT) {
            accepted++;
            if (r->verdict != ACCEPT) {
                print_error("%s: the parser accepts it, the schema does not: %s\n", r->path,
                            schema_why(r));
                bad++;
            }
        }
    }
    assert_true(accepted >= 8); /* the examples at least */
    if (bad)
        fail_msg("%zu accepted jobs are invalid under the schema", bad);
}

/* (2) Both accept or both reject, as the table says. */
static void test_agreement(void **unused)
{
    (void)unused;
    need_ajv();
    size_t n = sizeof AGREE / sizeof AGREE[0], bad = 0, accepts = 0;
    for (size_t i = 0; i < n; i++) {
        const agree_case *c = &AGREE[i];
        const ajv_result *r = &S.files[S.agree_first + i];
        mr_job_error err;
        verdict p = parser_verdict_quoted(c->json, &err);
        verdict s = (verdict)r->verdict;
        accepts += c->expect == ACCEPT;
        if (p != c->expect || s != c->expect) {
            print_error("agree %zu \"%s\": expected both to %s; parser %ss%s%s%s, schema %ss %s\n",
                        i, c->name, verdict_name(c->expect), verdict_name(p),
                        p == REJECT ? " (at '" : "", p == REJECT ? err.pointer : "",
                        p == REJECT ? "')" : "", verdict_name(s), schema_why(r));
            if (p == REJECT)
                print_error("    parser: %s\n", err.message);
            bad++;
        }
    }
    print_message("%zu agreement cases: %zu accepted and %zu rejected by both\n", n, accepts,
                  n - accepts);
    assert_true(n >= 30);
    if (bad)
        fail_msg("%zu of %zu agreement cases disagree", bad, n);
}

/* (3) What only the parser can check: the parser rejects, the schema
 * accepts, for the reason given. */
static void test_parser_only(void **unused)
{
    (void)unused;
    need_ajv();
    size_t n = sizeof PARSER_ONLY / sizeof PARSER_ONLY[0], bad = 0;
    for (size_t i = 0; i < n; i++) {
        const parser_only_case *c = &PARSER_ONLY[i];
        const ajv_result *r = &S.files[S.parser_only_first + i];
        mr_job_error err;
        verdict p = parser_verdict_quoted(c->json, &err);
        print_message("parser-only \"%s\" (%s): parser %ss at '%s': %s\n", c->name, c->why,
                      verdict_name(p), err.pointer, err.message);
        if (p != REJECT) {
            print_error("parser-only %zu \"%s\": the parser accepts it\n", i, c->name);
            bad++;
        }
        if (r->verdict != ACCEPT) {
            print_error("parser-only %zu \"%s\": the schema rejects it too (%s): make it an "
                        "agreement case\n",
                        i, c->name, schema_why(r));
            bad++;
        }
    }
    print_message("%zu parser-only cases\n", n);
    if (bad)
        fail_msg("%zu parser-only cases are not what the table says", bad);
}

int main(void)
{
    const struct CMUnitTest tests[] = {
        cmocka_unit_test(test_schema_current),
        cmocka_unit_test(test_ajv_ran),
        cmocka_unit_test(test_examples_and_data),
        cmocka_unit_test(test_agreement),
        cmocka_unit_test(test_parser_only),
    };
    return cmocka_run_group_tests(tests, setup, teardown);
}
