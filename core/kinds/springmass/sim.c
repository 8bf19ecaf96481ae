/* sim.c - spring-mass simulation on the node grid (sim.h). */
#include "kinds/springmass/sim.h"

#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#if defined(__x86_64__) || defined(__i386__)
#include <immintrin.h>
#define SM_X86 1
#endif

#include "math/mr_math.h"
#include "util/le.h"
#include "util/parallel.h"

/* Lanes read past a row's last cell by the widest kernel, plus slack. */
#define SM_SLACK 16u
/* Chunks per thread of a parallel pass over the rows: enough for one
 * thread to take over another's share when it is held up, few enough
 * that taking a chunk (an atomic add on a line both threads write) costs
 * nothing next to stepping it. */
#define SM_CHUNKS_PER_THREAD 8u

struct sm_sim {
    sm_grid grid;
    const mr_springmass_params *p;
    size_t cells;
    float *act, *surf;                  /* per cell: node 1/0, surface node 1/0 */
    float *rest[3], *pos[3], *next[3], *vel[3], *nrm[3], *nstr;
    float *rest_nrm[3], *rest_nstr;     /* the approximate normals at rest */
    /* the end-of-frame pass' per-cell figures (sim_kernel.h), summed per row */
    float *cell_kinetic, *cell_spring, *cell_gravity, *cell_shadow, *cell_strain, *cell_bound, *cell_bad,
        *cell_inv;
    ptrdiff_t off[18];
    float k[18], len[18], lmin[18];
    double inv_len[18];
    size_t span_count;
    uint32_t *span_begin, *span_end;    /* rows of the grid holding nodes: [begin, end) cells */
    uint8_t *span_pinned;               /* per span: holds a pinned node */
    uint8_t *pin_of;                    /* per cell: 0, or 1 + index of the pin holding it */
    mr_vec3 *pivot;                     /* per pin */
    int64_t *force_cell;                /* per force: the point force's node, -1 for wind */
    double h_crit;                      /* the stability bound of the last measured state */
    float h, hm, inv_den, mg[3];
    uint32_t substeps, forced_substeps, last_substeps;
    bool driven;
    /* state */
    uint64_t steps;
    double energy_ref, energy_scale;
    double rounding_heat;               /* energy float rounding may have added so far (sim.h) */
    double heat_per_substep;
    int failed_rc;
    char failed_msg[400];
    sm_measure m;
    double *row_sums;                   /* per span: measure partial sums */
};

/* A pin's motion at t: rotation matrix (row-major 3x3) and translation. */
typedef struct pin_motion {
    float r[9];
    float t[3];
    float pivot[3];
} pin_motion;

typedef struct constrain_ctx {
    sm_sim *sim;
    const pin_motion *pins;
    const mr_vec3 *probe0, *probe1; /* probe centres at the substep's start and end */
} constrain_ctx;

static void constrain_row(const constrain_ctx *x, size_t r);

typedef struct sm_step_ctx {
    const sm_sim *sim;
    float wind[3];
    /* pins and probes, applied by the kernel to each row it has stepped
     * when no point force comes between (substep): to the rows holding a
     * pinned node and those with a new position inside `reach`, a box
     * holding every probe's path over the substep with a margin */
    const constrain_ctx *constrain;
    float reach_lo[3], reach_hi[3];
} sm_step_ctx;

#define SMK_CAT2(a, b) a##b
#define SMK_CAT(a, b) SMK_CAT2(a, b)

/* Per row: kinetic, spring and gravity energy, the shadow term, the
 * largest strain, inverted cells, non-finite or out-of-range coordinates,
 * the largest stiffness bound B of a node (sim.h). */
enum { RS_T, RS_V, RS_G, RS_SH, RS_STRAIN, RS_INV, RS_BAD, RS_BOUND, RS_N };

/* Row r's sums of the per-cell figures, in cell order (doubles), and its
 * inverted cells. */
static void measure_row_sum(sm_sim *s, size_t r)
{
    double *sum = s->row_sums + r * RS_N;
    memset(sum, 0, RS_N * sizeof *sum);
    for (size_t c = s->span_begin[r]; c < s->span_end[r]; c++) {
        if (s->act[c] == 0)
            continue;
        sum[RS_T] += s->cell_kinetic[c];
        sum[RS_V] += s->cell_spring[c];
        sum[RS_G] += s->cell_gravity[c];
        sum[RS_SH] += s->cell_shadow[c];
        sum[RS_BAD] += s->cell_bad[c];
        double e = s->cell_strain[c], bnd = s->cell_bound[c];
        sum[RS_STRAIN] = e > sum[RS_STRAIN] || e != e ? e : sum[RS_STRAIN];
        sum[RS_BOUND] = bnd > sum[RS_BOUND] || bnd != bnd ? bnd : sum[RS_BOUND];
        sum[RS_INV] += s->cell_inv[c];
    }
}

/* The one-lane kernel: the reference every width must match. */
static inline float smk_sqrt1(float x) { return sqrtf(x); }
#define SMK_W 1
#define SMK_NAME step_rows_1
#define SMK_MEASURE measure_rows_1
#define SMK_ATTR
#define SMK_SQRT(v) ((smk_v1){smk_sqrt1((v)[0])})
#include "kinds/springmass/sim_kernel.h"
#undef SMK_W
#undef SMK_NAME
#undef SMK_MEASURE
#undef SMK_ATTR
#undef SMK_SQRT

#ifdef SM_X86
#define SMK_W 4
#define SMK_NAME step_rows_4
#define SMK_MEASURE measure_rows_4
#define SMK_ATTR
#define SMK_SQRT(v) ((smk_v4)_mm_sqrt_ps((__m128)(v)))
#include "kinds/springmass/sim_kernel.h"
#undef SMK_W
#undef SMK_NAME
#undef SMK_MEASURE
#undef SMK_ATTR
#undef SMK_SQRT

#define SMK_W 8
#define SMK_TAIL_W 4
#define SMK_NAME step_rows_8
#define SMK_MEASURE measure_rows_8
#define SMK_ATTR __attribute__((target("avx")))
#define SMK_SQRT(v) ((smk_v8)_mm256_sqrt_ps((__m256)(v)))
#include "kinds/springmass/sim_kernel.h"
#undef SMK_W
#undef SMK_TAIL_W
#undef SMK_NAME
#undef SMK_MEASURE
#undef SMK_ATTR
#undef SMK_SQRT
#endif

/* The widest kernel this CPU runs (all give the same bits). A test may
 * force a width: sm_sim_force_width. */
static int forced_width;

void sm_sim_force_width(int lanes) { forced_width = lanes; }

typedef struct kernels {
    mr_range_fn step, measure;
} kernels;

static kernels pick_kernels(void)
{
#ifdef SM_X86
    if (forced_width == 1)
        return (kernels){step_rows_1, measure_rows_1};
    if (forced_width == 4)
        return (kernels){step_rows_4, measure_rows_4};
    __builtin_cpu_init();
    if (__builtin_cpu_supports("avx"))
        return (kernels){step_rows_8, measure_rows_8};
    return (kernels){step_rows_4, measure_rows_4};
#else
    return (kernels){step_rows_1, measure_rows_1};
#endif
}

uint32_t sm_substeps(const mr_springmass_params *p, double *h_crit)
{
    double k = (double)p->stiffness + 2.0 * (double)p->shear_stiffness;
    double hc = k > 0 ? sqrt((double)p->mass / k) : INFINITY;
    if (h_crit)
        *h_crit = hc;
    double n = ceil((double)p->dt / (SM_STABLE_FRACTION * hc));
    if (!(n >= 1))
        n = 1;
    return n > SM_MAX_SUBSTEPS ? 0 : (uint32_t)n;
}

void sm_sim_free(sm_sim *s)
{
    if (!s)
        return;
    sm_grid_free(&s->grid);
    free(s->act);
    free(s->surf);
    for (int a = 0; a < 3; a++) {
        free(s->rest[a]);
        free(s->pos[a]);
        free(s->next[a]);
        free(s->vel[a]);
        free(s->nrm[a]);
        free(s->rest_nrm[a]);
    }
    free(s->nstr);
    free(s->rest_nstr);
    free(s->cell_kinetic);
    free(s->cell_spring);
    free(s->cell_gravity);
    free(s->cell_shadow);
    free(s->cell_strain);
    free(s->cell_bound);
    free(s->cell_bad);
    free(s->cell_inv);
    free(s->span_begin);
    free(s->span_end);
    free(s->span_pinned);
    free(s->pin_of);
    free(s->pivot);
    free(s->force_cell);
    free(s->row_sums);
    free(s);
}

const sm_grid *sm_sim_grid(const sm_sim *s) { return &s->grid; }
uint64_t sm_sim_steps(const sm_sim *s) { return s->steps; }
uint32_t sm_sim_substeps(const sm_sim *s) { return s->last_substeps ? s->last_substeps : s->substeps; }
const sm_measure *sm_sim_measure(const sm_sim *s) { return &s->m; }

void sm_sim_positions(const sm_sim *s, const float *xyz[3])
{
    for (int a = 0; a < 3; a++)
        xyz[a] = s->pos[a];
}
void sm_sim_rest(const sm_sim *s, const float *xyz[3])
{
    for (int a = 0; a < 3; a++)
        xyz[a] = s->rest[a];
}
void sm_sim_normals(const sm_sim *s, const float *xyz[3])
{
    for (int a = 0; a < 3; a++)
        xyz[a] = s->nrm[a];
}
const float *sm_sim_normal_strength(const sm_sim *s) { return s->nstr; }
void sm_sim_rest_normals(const sm_sim *s, const float *xyz[3], const float **strength)
{
    for (int a = 0; a < 3; a++)
        xyz[a] = s->rest_nrm[a];
    *strength = s->rest_nstr;
}

/* ---- paths */

/* Keys bracketing t (keys sorted by t, checked by the parser): i0, i1 and
 * the blend u in [0, 1]. */
#define KEY_SEARCH(keys, count, t, i0, i1, u)                                                      \
    do {                                                                                           \
        size_t lo_ = 0, hi_ = (count) - 1;                                                         \
        if ((t) <= (keys)[0].t) {                                                                  \
            i0 = i1 = 0;                                                                           \
        } else if ((t) >= (keys)[hi_].t) {                                                         \
            i0 = i1 = hi_;                                                                         \
        } else {                                                                                   \
            while (hi_ - lo_ > 1) {                                                                \
                size_t mid_ = (lo_ + hi_) / 2;                                                     \
                if ((keys)[mid_].t <= (t))                                                         \
                    lo_ = mid_;                                                                    \
                else                                                                               \
                    hi_ = mid_;                                                                    \
            }                                                                                      \
            i0 = lo_;                                                                              \
            i1 = hi_;                                                                              \
        }                                                                                          \
        u = i0 == i1 ? 0.0f : (float)(((t) - (keys)[i0].t) / ((keys)[i1].t - (keys)[i0].t));      \
    } while (0)

static pin_motion pin_at(const sm_sim *s, size_t pin, double t)
{
    const mr_springmass_pin *p = &s->p->pins[pin];
    pin_motion m = {{1, 0, 0, 0, 1, 0, 0, 0, 1}, {0, 0, 0}, {s->pivot[pin].x, s->pivot[pin].y, s->pivot[pin].z}};
    if (p->path_count == 0)
        return m;
    size_t i0, i1;
    float u;
    KEY_SEARCH(p->path, p->path_count, t, i0, i1, u);
    mr_vec3 tr = mr_v3_lerp(p->path[i0].translation, p->path[i1].translation, u);
    mr_quat q = i0 == i1 ? p->path[i0].rotation : mr_quat_slerp(p->path[i0].rotation, p->path[i1].rotation, u);
    q = mr_quat_normalize(q);
    mr_vec3 ex = mr_quat_rotate(q, mr_v3(1, 0, 0)), ey = mr_quat_rotate(q, mr_v3(0, 1, 0)),
            ez = mr_quat_rotate(q, mr_v3(0, 0, 1));
    float r[9] = {ex.x, ey.x, ez.x, ex.y, ey.y, ez.y, ex.z, ey.z, ez.z};
    memcpy(m.r, r, sizeof r);
    m.t[0] = tr.x;
    m.t[1] = tr.y;
    m.t[2] = tr.z;
    return m;
}

static mr_vec3 probe_at(const mr_springmass_probe *p, double t)
{
    size_t i0, i1;
    float u;
    KEY_SEARCH(p->path, p->path_count, t, i0, i1, u);
    return mr_v3_lerp(p->path[i0].position, p->path[i1].position, u);
}

/* ---- set-up */

static float *alloc_cells(size_t n)
{
    return calloc(n + SM_SLACK, sizeof(float));
}

/* The substep h and the factors of the kick that depend on it. */
static void set_step(sm_sim *s)
{
    s->h = (float)((double)s->p->dt / s->substeps);
    s->hm = s->h / s->p->mass;
    s->inv_den = 1.0f / (1.0f + s->h * s->p->damping / s->p->mass);
}

void sm_sim_set_substeps(sm_sim *s, uint32_t substeps, unsigned threads)
{
    s->forced_substeps = substeps;
    s->substeps = substeps ? substeps : 1;
    set_step(s);
    sm_sim_reset(s, threads);
}

static bool in_box(const mr_springmass_pin *p, float x, float y, float z)
{
    return !p->points_only && x >= p->box_min.x && x <= p->box_max.x && y >= p->box_min.y && y <= p->box_max.y &&
           z >= p->box_min.z && z <= p->box_max.z;
}

/* The node nearest to q at rest (ties: the lowest cell): the lattice
 * cells around q first, then every node. */
static size_t nearest_node_at(const sm_sim *s, mr_vec3 q)
{
    const sm_grid *g = &s->grid;
    double at[3] = {q.x, q.y, q.z}, best = INFINITY;
    size_t found = SIZE_MAX;
    int64_t c0[3];
    for (int a = 0; a < 3; a++)
        c0[a] = (int64_t)llround((at[a] - g->origin[a]) / g->h);
    for (int64_t dk = -2; dk <= 2; dk++)
        for (int64_t dj = -2; dj <= 2; dj++)
            for (int64_t di = -2; di <= 2; di++) {
                int64_t i = c0[0] + di, j = c0[1] + dj, k = c0[2] + dk;
                if (i < 0 || j < 0 || k < 0 || i >= g->n[0] || j >= g->n[1] || k >= g->n[2])
                    continue;
                size_t c = sm_grid_cell(g, (uint32_t)i, (uint32_t)j, (uint32_t)k);
                double dx = s->rest[0][c] - at[0], dy = s->rest[1][c] - at[1], dz = s->rest[2][c] - at[2];
                double d2 = dx * dx + dy * dy + dz * dz;
                if (g->active[c] && (d2 < best || (d2 == best && c < found))) {
                    best = d2;
                    found = c;
                }
            }
    if (found != SIZE_MAX && sqrt(best) <= 1.5 * g->h) /* nothing closer lies outside the block */
        return found;
    for (size_t c = 0; c < s->cells; c++) {
        double dx = s->rest[0][c] - at[0], dy = s->rest[1][c] - at[1], dz = s->rest[2][c] - at[2];
        double d2 = dx * dx + dy * dy + dz * dz;
        if (g->active[c] && d2 < best) {
            best = d2;
            found = c;
        }
    }
    return found;
}

static int measure(sm_sim *s, unsigned threads);

int sm_sim_new(sm_grid *grid, const mr_springmass_params *p, unsigned threads, sm_sim **out,
               mr_error *err)
{
    *out = NULL;
    sm_sim *s = calloc(1, sizeof *s);
    if (!s) {
        sm_grid_free(grid);
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory");
    }
    s->grid = *grid;
    memset(grid, 0, sizeof *grid);
    s->p = p;
    const sm_grid *g = &s->grid;
    s->cells = g->cells;
    s->act = alloc_cells(s->cells);
    s->surf = alloc_cells(s->cells);
    s->nstr = alloc_cells(s->cells);
    s->rest_nstr = alloc_cells(s->cells);
    s->pin_of = calloc(s->cells + SM_SLACK, 1);
    s->cell_kinetic = alloc_cells(s->cells);
    s->cell_spring = alloc_cells(s->cells);
    s->cell_gravity = alloc_cells(s->cells);
    s->cell_shadow = alloc_cells(s->cells);
    s->cell_strain = alloc_cells(s->cells);
    s->cell_bound = alloc_cells(s->cells);
    s->cell_bad = alloc_cells(s->cells);
    s->cell_inv = alloc_cells(s->cells);
    bool ok = s->act && s->surf && s->nstr && s->rest_nstr && s->pin_of && s->cell_kinetic && s->cell_spring &&
              s->cell_gravity && s->cell_shadow && s->cell_strain && s->cell_bound && s->cell_bad &&
              s->cell_inv;
    for (int a = 0; a < 3 && ok; a++)
        ok = (s->rest[a] = alloc_cells(s->cells)) && (s->pos[a] = alloc_cells(s->cells)) &&
             (s->next[a] = alloc_cells(s->cells)) && (s->vel[a] = alloc_cells(s->cells)) &&
             (s->nrm[a] = alloc_cells(s->cells)) && (s->rest_nrm[a] = alloc_cells(s->cells));
    if (!ok)
        goto nomem;
    for (uint32_t k = 0; k < g->n[2]; k++)
        for (uint32_t j = 0; j < g->n[1]; j++)
            for (uint32_t i = 0; i < g->n[0]; i++) {
                size_t c = sm_grid_cell(g, i, j, k);
                s->act[c] = g->active[c] ? 1.0f : 0.0f;
                s->surf[c] = (g->flags[c] & SM_NODE_SURFACE) ? 1.0f : 0.0f;
                double q[3] = {g->origin[0] + g->h * i, g->origin[1] + g->h * j, g->origin[2] + g->h * k};
                for (int a = 0; a < 3; a++)
                    s->rest[a][c] = (float)q[a];
            }
    /* rows holding nodes */
    size_t rows = (size_t)g->n[1] * g->n[2];
    s->span_begin = malloc(rows * sizeof *s->span_begin);
    s->span_end = malloc(rows * sizeof *s->span_end);
    if (!s->span_begin || !s->span_end)
        goto nomem;
    for (size_t r = 0; r < rows; r++) {
        size_t c0 = r * g->n[0], first = SIZE_MAX, last = 0;
        for (size_t i = 0; i < g->n[0]; i++)
            if (g->active[c0 + i]) {
                if (first == SIZE_MAX)
                    first = c0 + i;
                last = c0 + i;
            }
        if (first != SIZE_MAX) {
            s->span_begin[s->span_count] = (uint32_t)first;
            s->span_end[s->span_count++] = (uint32_t)(last + 1);
        }
    }
    if (!(s->row_sums = calloc(s->span_count * 8 + 1, sizeof *s->row_sums)))
        goto nomem;
    double h = g->h;
    for (int d = 0; d < 18; d++) {
        s->off[d] = sm_grid_offset(g, sm_neighbour_dir[d]);
        bool axis = d < 6;
        s->k[d] = axis ? p->stiffness : p->shear_stiffness;
        s->len[d] = (float)(axis ? h : h * sqrt(2.0));
        s->lmin[d] = s->len[d] * 1e-6f;
        s->inv_len[d] = 1.0 / s->len[d];
    }
    /* float rounding of positions near the largest coordinate (ulp u)
     * perturbs every spring's stretch by about u each substep: it may add
     * k u^2 of energy per spring (sim.h) */
    {
        double springs = 0, big = 0;
        for (size_t c = 0; c < s->cells; c++) {
            if (!g->active[c])
                continue;
            for (int d = 0; d < 18; d++)
                springs += g->active[(size_t)((ptrdiff_t)c + s->off[d])] ? 0.5 : 0;
            for (int a = 0; a < 3; a++)
                big = fmax(big, fabs((double)s->rest[a][c]));
        }
        double u = (big + g->h * g->n[0] + g->h * g->n[1] + g->h * g->n[2]) * ldexp(1.0, -23);
        s->heat_per_substep = springs * fmax(p->stiffness, p->shear_stiffness) * u * u;
    }
    s->substeps = sm_substeps(p, &s->h_crit);
    if (s->substeps == 0) { /* the parser refuses such jobs */
        sm_sim_free(s);
        return mr_error_set(err, MR_ERR_LIMIT, "dt needs more than %u substeps", SM_MAX_SUBSTEPS);
    }
    set_step(s);
    s->mg[0] = p->mass * p->gravity.x;
    s->mg[1] = p->mass * p->gravity.y;
    s->mg[2] = p->mass * p->gravity.z;
    /* pins: the first pin whose box or node set holds a node takes it */
    if (p->pin_count) {
        if (!(s->pivot = calloc(p->pin_count, sizeof *s->pivot)))
            goto nomem;
        double *sum = calloc(p->pin_count * 4, sizeof *sum);
        uint8_t *in_set = calloc(s->cells + 1, 1); /* the first pin whose node set holds the cell */
        if (!sum || !in_set) {
            free(sum);
            free(in_set);
            goto nomem;
        }
        for (size_t q = p->pin_count; q-- > 0;)
            for (size_t k = 0; k < p->pins[q].point_count; k++) {
                size_t c = nearest_node_at(s, p->pins[q].points[k].position);
                if (c != SIZE_MAX)
                    in_set[c] = (uint8_t)(q + 1);
            }
        for (size_t c = 0; c < s->cells; c++) {
            if (!g->active[c])
                continue;
            for (size_t q = 0; q < p->pin_count; q++)
                if (in_set[c] == q + 1 || in_box(&p->pins[q], s->rest[0][c], s->rest[1][c], s->rest[2][c])) {
                    s->pin_of[c] = (uint8_t)(q + 1);
                    sum[q * 4] += s->rest[0][c];
                    sum[q * 4 + 1] += s->rest[1][c];
                    sum[q * 4 + 2] += s->rest[2][c];
                    sum[q * 4 + 3] += 1;
                    break;
                }
        }
        for (size_t q = 0; q < p->pin_count; q++) {
            const mr_springmass_pin *pin = &p->pins[q];
            double n = sum[q * 4 + 3] > 0 ? sum[q * 4 + 3] : 1;
            s->pivot[q] = pin->has_pivot ? pin->pivot
                                         : mr_v3((float)(sum[q * 4] / n), (float)(sum[q * 4 + 1] / n),
                                                 (float)(sum[q * 4 + 2] / n));
            s->driven |= pin->path_count > 0;
        }
        free(sum);
        free(in_set);
    }
    if (!(s->span_pinned = calloc(s->span_count + 1, 1)))
        goto nomem;
    for (size_t r = 0; r < s->span_count; r++)
        for (size_t c = s->span_begin[r]; c < s->span_end[r]; c++)
            s->span_pinned[r] |= s->pin_of[c] != 0;
    s->driven |= p->probe_count > 0 || p->force_count > 0;
    if (p->force_count) {
        if (!(s->force_cell = malloc(p->force_count * sizeof *s->force_cell)))
            goto nomem;
        for (size_t f = 0; f < p->force_count; f++) {
            s->force_cell[f] = -1;
            if (p->forces[f].type != MR_SPRINGMASS_FORCE_POINT)
                continue;
            double best = INFINITY;
            mr_vec3 at = p->forces[f].position;
            for (size_t c = 0; c < s->cells; c++) {
                if (!g->active[c])
                    continue;
                double dx = s->rest[0][c] - at.x, dy = s->rest[1][c] - at.y, dz = s->rest[2][c] - at.z;
                double d2 = dx * dx + dy * dy + dz * dz;
                if (d2 < best) {
                    best = d2;
                    s->force_cell[f] = (int64_t)c;
                }
            }
        }
    }
    *out = s;
    sm_sim_reset(s, threads);
    for (int a = 0; a < 3; a++)
        memcpy(s->rest_nrm[a], s->nrm[a], s->cells * sizeof(float));
    memcpy(s->rest_nstr, s->nstr, s->cells * sizeof(float));
    return MR_OK;
nomem:
    sm_sim_free(s);
    return mr_error_set(err, MR_ERR_NOMEM, "out of memory for the simulation of %zu cells", g->cells);
}

void sm_sim_reset(sm_sim *s, unsigned threads)
{
    for (int a = 0; a < 3; a++) {
        memcpy(s->pos[a], s->rest[a], s->cells * sizeof(float));
        memcpy(s->next[a], s->rest[a], s->cells * sizeof(float));
        memset(s->vel[a], 0, s->cells * sizeof(float));
    }
    s->steps = 0;
    s->last_substeps = 0;
    s->failed_rc = MR_OK;
    s->failed_msg[0] = 0;
    s->energy_scale = 0;
    s->rounding_heat = 0;
    measure(s, threads);
    s->energy_ref = s->m.shadow;
}

/* ---- the passes */

/* Pins and probes on next[] of row r's nodes (pins win), velocities from
 * the move. */
static void constrain_row(const constrain_ctx *x, size_t r)
{
    sm_sim *s = x->sim;
    const mr_springmass_params *p = s->p;
    const float inv_h = 1.0f / s->h;
    for (size_t c = s->span_begin[r]; c < s->span_end[r]; c++) {
        if (s->act[c] == 0)
            continue;
        float q[3] = {s->next[0][c], s->next[1][c], s->next[2][c]};
        bool moved = false;
        if (s->pin_of[c]) {
            const pin_motion *m = &x->pins[s->pin_of[c] - 1];
            float d[3] = {s->rest[0][c] - m->pivot[0], s->rest[1][c] - m->pivot[1],
                          s->rest[2][c] - m->pivot[2]};
            /* as a displacement from rest, so a pin that does not move
             * holds its nodes exactly at rest */
            for (int a = 0; a < 3; a++)
                q[a] = s->rest[a][c] +
                       (((m->r[a * 3] * d[0] + m->r[a * 3 + 1] * d[1] + m->r[a * 3 + 2] * d[2]) - d[a]) + m->t[a]);
            moved = true;
        } else {
            for (size_t k = 0; k < p->probe_count; k++) {
                const mr_vec3 c0 = x->probe0[k], c1 = x->probe1[k];
                const float rad = p->probes[k].radius;
                float seg[3] = {c1.x - c0.x, c1.y - c0.y, c1.z - c0.z};
                float rel[3] = {q[0] - c0.x, q[1] - c0.y, q[2] - c0.z};
                float ss = seg[0] * seg[0] + seg[1] * seg[1] + seg[2] * seg[2];
                float u = ss > 0 ? (rel[0] * seg[0] + rel[1] * seg[1] + rel[2] * seg[2]) / ss : 1.0f;
                u = u < 0 ? 0 : u > 1 ? 1 : u;
                float at[3] = {c0.x + u * seg[0], c0.y + u * seg[1], c0.z + u * seg[2]};
                float dv[3] = {q[0] - at[0], q[1] - at[1], q[2] - at[2]};
                float d2 = dv[0] * dv[0] + dv[1] * dv[1] + dv[2] * dv[2];
                if (!(d2 < rad * rad))
                    continue;
                float dist = sqrtf(d2);
                if (dist > rad * 1e-6f) {
                    for (int a = 0; a < 3; a++)
                        q[a] = at[a] + dv[a] * (rad / dist);
                } else { /* on the path itself: out along +y */
                    q[0] = at[0];
                    q[1] = at[1] + rad;
                    q[2] = at[2];
                }
                moved = true;
            }
        }
        if (moved)
            for (int a = 0; a < 3; a++) {
                s->vel[a][c] = (q[a] - s->pos[a][c]) * inv_h;
                s->next[a][c] = q[a];
            }
    }
}

static void constrain_rows(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    for (size_t r = begin; r < end; r++)
        constrain_row(ctx, r);
}

/* The box every node a probe may move this substep lies in: the probes'
 * paths from c0 to c1 widened by their radius, plus a margin for the
 * rounding of the test in constrain_row (its closest point on the path
 * and squared distance). Empty (lo > hi) without probes. */
static void probe_reach(const mr_springmass_params *p, const mr_vec3 *c0, const mr_vec3 *c1, float lo[3],
                        float hi[3])
{
    for (int a = 0; a < 3; a++) {
        lo[a] = INFINITY;
        hi[a] = -INFINITY;
    }
    for (size_t k = 0; k < p->probe_count; k++) {
        const float a0[3] = {c0[k].x, c0[k].y, c0[k].z}, a1[3] = {c1[k].x, c1[k].y, c1[k].z};
        for (int a = 0; a < 3; a++) {
            float big = fmaxf(fabsf(a0[a]), fabsf(a1[a]));
            float margin = p->probes[k].radius * 1.001f + big * 1e-5f + 1e-30f;
            lo[a] = fminf(lo[a], fminf(a0[a], a1[a]) - margin);
            hi[a] = fmaxf(hi[a], fmaxf(a0[a], a1[a]) + margin);
        }
    }
}

static size_t row_grain(const sm_sim *s, unsigned threads)
{
    size_t g = s->span_count / ((size_t)(threads ? threads : mr_cpu_count()) * SM_CHUNKS_PER_THREAD);
    return g ? g : 1;
}

static void substep(sm_sim *s, double t0, unsigned threads, mr_range_fn kernel)
{
    const mr_springmass_params *p = s->p;
    double t1 = t0 + s->h;
    sm_step_ctx sc = {.sim = s};
    for (size_t f = 0; f < p->force_count; f++) {
        const mr_springmass_force *fo = &p->forces[f];
        if (fo->type == MR_SPRINGMASS_FORCE_WIND && t0 >= fo->start && t0 < fo->end) {
            sc.wind[0] += fo->force.x;
            sc.wind[1] += fo->force.y;
            sc.wind[2] += fo->force.z;
        }
    }
    bool point_forces = false;
    for (size_t f = 0; f < p->force_count; f++) {
        const mr_springmass_force *fo = &p->forces[f];
        point_forces |= s->force_cell[f] >= 0 && t0 >= fo->start && t0 < fo->end;
    }
    const bool constrained = p->pin_count || p->probe_count;
    pin_motion pins[MR_SPRINGMASS_MAX_PINS];
    mr_vec3 c0[MR_SPRINGMASS_MAX_PROBES], c1[MR_SPRINGMASS_MAX_PROBES];
    for (size_t q = 0; q < p->pin_count; q++)
        pins[q] = pin_at(s, q, t1);
    for (size_t q = 0; q < p->probe_count; q++) {
        c0[q] = probe_at(&p->probes[q], t0);
        c1[q] = probe_at(&p->probes[q], t1);
    }
    constrain_ctx cc = {s, pins, c0, c1};
    /* without point forces the kernel constrains each row right after
     * stepping it (the same operations on the same values: a row's
     * constraints read its own new positions and the old ones, which no
     * other row's step writes), and only rows a pin or probe can touch */
    if (constrained && !point_forces) {
        sc.constrain = &cc;
        probe_reach(p, c0, c1, sc.reach_lo, sc.reach_hi);
    }
    mr_parallel_for(threads, s->span_count, row_grain(s, threads), kernel, &sc);
    if (point_forces) {
        /* point forces: the kick and drift they add to their node */
        for (size_t f = 0; f < p->force_count; f++) {
            const mr_springmass_force *fo = &p->forces[f];
            int64_t c = s->force_cell[f];
            if (c < 0 || !(t0 >= fo->start && t0 < fo->end))
                continue;
            float fv[3] = {fo->force.x, fo->force.y, fo->force.z};
            for (int a = 0; a < 3; a++) {
                float dv = s->hm * fv[a] * s->inv_den;
                s->vel[a][c] += dv;
                s->next[a][c] += s->h * dv;
            }
        }
        if (constrained)
            mr_parallel_for(threads, s->span_count, row_grain(s, threads), constrain_rows, &cc);
    }
    for (int a = 0; a < 3; a++) {
        float *t = s->pos[a];
        s->pos[a] = s->next[a];
        s->next[a] = t;
    }
}

static int measure(sm_sim *s, unsigned threads)
{
    mr_parallel_for(threads, s->span_count, row_grain(s, threads), pick_kernels().measure, s);
    sm_measure m = {0};
    double bad = 0, inv = 0, bound = 0;
    for (size_t r = 0; r < s->span_count; r++) {
        const double *sum = s->row_sums + r * RS_N;
        bound = sum[RS_BOUND] > bound || sum[RS_BOUND] != sum[RS_BOUND] ? sum[RS_BOUND] : bound;
        m.kinetic += sum[RS_T];
        m.spring += sum[RS_V];
        m.gravity += sum[RS_G];
        m.shadow += sum[RS_SH];
        m.max_strain = sum[RS_STRAIN] > m.max_strain || sum[RS_STRAIN] != sum[RS_STRAIN] ? sum[RS_STRAIN]
                                                                                        : m.max_strain;
        inv += sum[RS_INV];
        bad += sum[RS_BAD];
    }
    m.shadow += m.kinetic + m.spring + m.gravity;
    m.inverted_cells = (uint32_t)inv;
    m.finite = bad == 0 && isfinite(m.shadow) && isfinite(m.max_strain);
    s->m = m;
    double scale = m.kinetic + m.spring + fabs(m.gravity);
    if (scale > s->energy_scale || !isfinite(scale))
        s->energy_scale = scale;
    /* the stability bound of this state: omega^2 <= 2 B / m (sim.h) */
    s->h_crit = bound > 0 ? sqrt(2.0 * s->p->mass / bound) : INFINITY;
    if (!s->forced_substeps) {
        double n = ceil((double)s->p->dt / (SM_STABLE_FRACTION * s->h_crit));
        s->substeps = !(n >= 1) ? 1 : n > SM_MAX_SUBSTEPS ? SM_MAX_SUBSTEPS + 1 : (uint32_t)n;
        set_step(s);
    }
    return MR_OK;
}

static int fail(sm_sim *s, mr_error *err, const char *fmt, ...)
    __attribute__((format(printf, 3, 4)));
static int fail(sm_sim *s, mr_error *err, const char *fmt, ...)
{
    char why[160];
    va_list ap;
    va_start(ap, fmt);
    vsnprintf(why, sizeof why, fmt, ap);
    va_end(ap);
    snprintf(s->failed_msg, sizeof s->failed_msg,
             "the simulation diverged by t = %.6g s (step %llu): %s; dt %g s is split into %u "
             "substeps (stability bound %.3g s)",
             (double)s->steps * s->p->dt, (unsigned long long)s->steps, why, (double)s->p->dt,
             s->substeps, s->h_crit);
    s->failed_rc = MR_ERR_INVALID;
    return mr_error_set(err, s->failed_rc, "%s", s->failed_msg);
}

int sm_sim_advance(sm_sim *s, uint64_t steps, unsigned threads, mr_error *err)
{
    if (s->failed_rc < 0)
        return mr_error_set(err, s->failed_rc, "%s", s->failed_msg);
    mr_range_fn kernel = pick_kernels().step;
    s->last_substeps = s->substeps;
    if (steps && s->substeps > SM_MAX_SUBSTEPS)
        return fail(s, err, "the springs stiffened (stretched) until a step needs more than %u substeps",
                    SM_MAX_SUBSTEPS);
    for (uint64_t k = 0; k < steps; k++) {
        double t = (double)s->steps * s->p->dt;
        for (uint32_t q = 0; q < s->substeps; q++)
            substep(s, t + (double)q * s->h, threads, kernel);
        s->steps++;
        s->rounding_heat += s->heat_per_substep * s->substeps;
    }
    measure(s, threads);
    const sm_measure *m = &s->m;
    if (!m->finite)
        return fail(s, err, "a node coordinate is not finite or beyond %g", MR_MAX_COORDINATE);
    if (m->max_strain > SM_MAX_STRAIN)
        return fail(s, err, "a spring is strained %.3g times its rest length", m->max_strain);
    if (!s->driven && m->shadow > s->energy_ref + SM_ENERGY_GROWTH * s->energy_scale + s->rounding_heat + 1e-30)
        return fail(s, err, "the energy grew from %.6g to %.6g with nothing driving it", s->energy_ref,
                    m->shadow);
    return MR_OK;
}

void sm_sim_perturb(sm_sim *s, float amplitude, uint32_t seed, unsigned threads)
{
    uint64_t st = seed * 0x9E3779B97F4A7C15ull + 1;
    for (size_t c = 0; c < s->cells; c++) {
        if (s->act[c] == 0 || s->pin_of[c])
            continue;
        for (int a = 0; a < 3; a++) {
            st = st * 6364136223846793005ull + 1442695040888963407ull;
            float u = (float)((st >> 40) * (1.0 / 16777216.0)) * 2.0f - 1.0f;
            s->pos[a][c] += amplitude * u;
        }
    }
    measure(s, threads);
    s->energy_ref = s->m.shadow;
}

/* ---- state */

#define STATE_HEAD 32u

size_t sm_sim_state_bytes(const sm_sim *s) { return STATE_HEAD + s->grid.nodes * 24; }

void sm_sim_state_save(const sm_sim *s, uint8_t *buf)
{
    mr_le_put_u64(buf, s->steps);
    mr_le_put_f64(buf + 8, s->energy_ref);
    mr_le_put_f64(buf + 16, s->energy_scale);
    mr_le_put_f64(buf + 24, s->rounding_heat);
    uint8_t *p = buf + STATE_HEAD;
    for (size_t c = 0; c < s->cells; c++) {
        if (!s->grid.active[c])
            continue;
        for (int a = 0; a < 3; a++)
            mr_le_put_f32(p + 4 * a, s->pos[a][c]);
        for (int a = 0; a < 3; a++)
            mr_le_put_f32(p + 12 + 4 * a, s->vel[a][c]);
        p += 24;
    }
}

int sm_sim_state_load(sm_sim *s, const uint8_t *buf, size_t size, unsigned threads, mr_error *err)
{
    if (size != sm_sim_state_bytes(s))
        return mr_error_set(err, MR_ERR_FORMAT, "simulation state of %zu bytes, expected %zu for %zu nodes",
                            size, sm_sim_state_bytes(s), s->grid.nodes);
    double ref = mr_le_get_f64(buf + 8), scale = mr_le_get_f64(buf + 16), heat = mr_le_get_f64(buf + 24);
    if (!isfinite(ref) || !isfinite(scale) || !(heat >= 0 && heat < INFINITY))
        return mr_error_set(err, MR_ERR_FORMAT, "simulation state: energy reference is not finite");
    for (size_t i = 0; i < s->grid.nodes * 6; i++) {
        float v = mr_le_get_f32(buf + STATE_HEAD + 4 * i);
        if (!(fabsf(v) <= MR_MAX_COORDINATE))
            return mr_error_set(err, MR_ERR_FORMAT, "simulation state: value %zu of node %zu is %g",
                                i % 6, i / 6, (double)v);
    }
    s->steps = mr_le_get_u64(buf);
    s->energy_ref = ref;
    s->energy_scale = scale;
    s->rounding_heat = heat;
    s->failed_rc = MR_OK;
    s->failed_msg[0] = 0;
    const uint8_t *p = buf + STATE_HEAD;
    for (size_t c = 0; c < s->cells; c++) {
        if (!s->grid.active[c])
            continue;
        for (int a = 0; a < 3; a++) {
            s->pos[a][c] = mr_le_get_f32(p + 4 * a);
            s->vel[a][c] = mr_le_get_f32(p + 12 + 4 * a);
        }
        p += 24;
    }
    measure(s, threads);
    return MR_OK;
}
