/*
 * sim.h - the spring-mass simulation on the node grid (paper 001, 3.1).
 *
 * Forces. A spring between nodes i and j with stiffness k and rest length
 * l pulls i by k (|d| - l) d / |d|, d = p_j - p_i: eq. 1 with our k the
 * stiffness of one spring (eq. 1 writes 1/2 k_ij because the paper counts
 * each spring at both of its nodes; REFERENCE.md). The 6 axis springs have
 * rest length h and stiffness k_s, the 12 face-diagonal ones h sqrt 2 and
 * k_d (eq. 2 has all k equal). Each node also feels m g, the viscous
 * damping -c v, wind on surface nodes and point forces.
 *
 * Integrator: semi-implicit (symplectic) Euler with the damping implicit,
 *   v' = (v + h F(x) / m) / (1 + h c / m),   x' = x + h v',
 * then kinematic constraints on x' (pins, probes) with v' = (x' - x) / h:
 * applied by the step kernel to each row right after stepping it, to rows
 * holding a pinned node or a new position within reach of a probe (a
 * row's constraints read only its own new positions), or, when a point
 * force acts in between, in a pass of their own.
 * Stability bound (docs/springmass.md). Symplectic Euler is stable while
 * h omega_max < 2 (omega_max^2 the largest eigenvalue of the stiffness
 * matrix K over m; the implicit damping only shrinks the growth factor).
 * For a node i let S_i = sum_j k_j u_j u_j^T over its springs (u_j =
 * d_j / |d_j|) and B_i = q + 2 p + sum_j k_j max(0, 1 - l_j / |d_j|), with
 * q = tr(S_i) / 3 and p = sqrt(|S_i - q I|_F^2 / 6): q + 2 p bounds the
 * largest eigenvalue of S_i (Smith's closed form is q + 2 p cos phi) and
 * the sum the transverse stiffness stretched springs add. Since (a - b)^2
 * <= 2 a^2 + 2 b^2, x^T K x <= 2 max_i B_i |x|^2, so h_crit =
 * sqrt(2 m / max_i B_i) is a bound (and a turned body keeps its bound). At rest an interior node
 * has B = 2 k_s + 4 k_d and the bound is attained (planes of nodes moving
 * against each other along an axis: eigenvalue 4 k_s + 8 k_d), so
 *   h_crit = sqrt(m / (k_s + 2 k_d))   at rest,
 * which the job is checked against (sm_substeps; tests/unit/
 * test_springmass_sim.c shows 0.97 h_crit stable and 1.03 h_crit blowing
 * up). After every frame the bound of the current state sets the next
 * frame's substeps: ceil(dt / (SM_STABLE_FRACTION h_crit)), reported in
 * the stats; the margin covers what changes within one frame. More than
 * SM_MAX_SUBSTEPS substeps per step are refused: with the job when the
 * rest state needs them, as a frame error when stretching does.
 *
 * Divergence is a frame error, never a rendered explosion: a coordinate
 * that is not finite or beyond MR_MAX_COORDINATE, a spring strain
 * (|d| / l - 1) above SM_MAX_STRAIN, or, when nothing drives the system
 * (no moving pin, probe or force: only gravity and springs), a growth of
 * the shadow energy the integrator conserves for linear forces,
 *   E = T + V + (h / 2) v . F(x)
 * (T kinetic, V spring plus gravity potential relative to the rest
 * positions, F the conservative force), by more than SM_ENERGY_GROWTH of
 * the largest energy magnitude seen. Symplectic Euler keeps E constant for
 * linear forces and damping only lowers it, so growth means instability,
 * not the ordinary exchange of kinetic and potential energy; the springs'
 * geometric nonlinearity lets it drift by up to 14 % over 60,000 undamped
 * steps at 0.9 h_crit (measured), an instability multiplies it within a few
 * frames. Float positions add energy of their own: rounding a coordinate
 * of size X moves a node by up to u = X 2^-23 each substep, which may put
 * k u^2 into each spring; the check allows the sum of that over the
 * substeps so far (very stiff springs, k = 1e7, heat by about 0.01 per
 * frame of a 400-node ball: measured; damping holds it).
 *
 * Determinism: every node's update reads only the previous positions, and
 * each sum runs over the 18 neighbours in sm_neighbour_dir order; lanes of
 * SIMD vectors compute exactly the scalar operation sequence (IEEE add,
 * multiply, divide and square root round the same in every width), and the
 * frame's energy sums are per row of the grid, added in row order. So the
 * state after any step is the same bits for any thread count and vector
 * width.
 */
#ifndef SM_SIM_H
#define SM_SIM_H

#include <stdbool.h>
#include <stddef.h>
#include <stdint.h>

#include "kinds/springmass/grid.h"
#include "kinds/springmass/springmass_kind.h"
#include "microray.h"

#define SM_STABLE_FRACTION 0.9
#define SM_MAX_SUBSTEPS 1000u
#define SM_MAX_STRAIN 100.0
#define SM_ENERGY_GROWTH 0.5

/* Substeps per step at rest for these parameters (>= 1), and the rest
 * bound h_crit; 0 when more than SM_MAX_SUBSTEPS would be needed. */
uint32_t sm_substeps(const mr_springmass_params *p, double *h_crit);

typedef struct sm_sim sm_sim;

/* What the end-of-frame pass measured. */
typedef struct sm_measure {
    double kinetic, spring, gravity; /* energies; gravity relative to rest */
    double shadow;                   /* E of the integrator (above) */
    double max_strain;               /* largest |d| / l - 1 in magnitude */
    uint32_t inverted_cells;         /* cells with a corner of non-positive volume */
    bool finite;                     /* every coordinate finite and within range */
} sm_measure;

/* A simulation of grid (taken over: freed with the simulation) under p
 * (borrowed; must outlive the simulation). Starts at rest, t = 0. */
int sm_sim_new(sm_grid *grid, const mr_springmass_params *p, unsigned threads, sm_sim **out,
               mr_error *err);
void sm_sim_free(sm_sim *s);
const sm_grid *sm_sim_grid(const sm_sim *s);

/* Back to rest: positions at rest, velocities 0, t = 0 (and measured). */
void sm_sim_reset(sm_sim *s, unsigned threads);
/* Advances `steps` steps of dt (each of sm_substeps substeps), then
 * measures (normals, energies, strain, inverted cells) and checks for
 * divergence: MR_ERR_INVALID with the reason (the caller names the
 * object). After a failure every further advance fails the same way until
 * sm_sim_reset. */
int sm_sim_advance(sm_sim *s, uint64_t steps, unsigned threads, mr_error *err);
/* Steps of dt taken since rest. */
uint64_t sm_sim_steps(const sm_sim *s);
/* Substeps per step the last advance took (before any: the next's, set
 * by the measured rest state). */
uint32_t sm_sim_substeps(const sm_sim *s);
const sm_measure *sm_sim_measure(const sm_sim *s);

/* Per-cell arrays (cells of the grid): current positions and the
 * approximate normals of eq. 3 (unit, or zero where the unit vectors
 * cancel) as of the last advance; rest positions. */
void sm_sim_positions(const sm_sim *s, const float *xyz[3]);
void sm_sim_rest(const sm_sim *s, const float *xyz[3]);
void sm_sim_normals(const sm_sim *s, const float *xyz[3]);
/* The approximate normal's length before normalising (the sum of up to 18
 * unit vectors), per cell: how well it is defined. */
const float *sm_sim_normal_strength(const sm_sim *s);
/* Both at rest (what the mappings bind with). */
void sm_sim_rest_normals(const sm_sim *s, const float *xyz[3], const float **strength);

/* Test hook: the step kernel's vector width (1, 4 or 8 lanes; 0: the
 * widest the CPU runs). Every width gives the same bits. */
void sm_sim_force_width(int lanes);
/* Test hook: the substeps per step, whatever the stability bound says
 * (to show that the bound is where instability starts), then back to
 * rest. */
void sm_sim_set_substeps(sm_sim *s, uint32_t substeps, unsigned threads);
/* Test hook: moves every unpinned node by a uniform random offset of at
 * most amplitude per axis (seeded, deterministic), velocities unchanged,
 * and re-measures. */
void sm_sim_perturb(sm_sim *s, float amplitude, uint32_t seed, unsigned threads);

/* The state as bytes (steps, the energy check's reference, scale and
 * rounding allowance, then per node position and velocity, in cell order,
 * little-endian) and back. Load checks the size and that every
 * value is finite, and changes nothing on failure. */
size_t sm_sim_state_bytes(const sm_sim *s);
void sm_sim_state_save(const sm_sim *s, uint8_t *buf);
int sm_sim_state_load(sm_sim *s, const uint8_t *buf, size_t size, unsigned threads, mr_error *err);

#endif
