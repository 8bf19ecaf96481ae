/*
 * sim_kernel.h - the step kernel of sim.c (force, kick and drift of every
 * node of a range of grid rows), included by sim.c once per vector width.
 * The includer defines:
 *   SMK_W      lanes per vector
 *   SMK_NAME   the step function's name
 *   SMK_MEASURE the measure function's name (sim.c's end-of-frame pass:
 *              per node the approximate normal of eq. 3, its energies,
 *              largest strain and stiffness bound into per-cell arrays,
 *              then measure_row_sum for each row)
 *   SMK_TAIL_W (optional) a narrower width included before, for the last
 *              nodes of a row
 *   SMK_ATTR   function attributes (a target ISA), may be empty
 *   SMK_SQRT   vector square root (x)
 * Every lane computes exactly the operation sequence of one node, so all
 * widths give the same bits (sim.h).
 */

typedef float SMK_CAT(smk_v, SMK_W) __attribute__((vector_size(4 * SMK_W)));
typedef int32_t SMK_CAT(smk_i, SMK_W) __attribute__((vector_size(4 * SMK_W)));
#define SMK_V SMK_CAT(smk_v, SMK_W)
#define SMK_I SMK_CAT(smk_i, SMK_W)

/* The step's constants, as vectors. */
typedef struct SMK_CAT(smk_step_k, SMK_W) {
    SMK_V vh, vhm, vinv, vmgx, vmgy, vmgz, vwx, vwy, vwz, vk[18], vl[18], vlmin[18], lox, loy, loz, hix, hiy, hiz;
} SMK_CAT(smk_step_k, SMK_W);

SMK_ATTR static inline void SMK_CAT(step_consts_, SMK_W)(const sm_step_ctx *x, SMK_CAT(smk_step_k, SMK_W) *k)
{
    const sm_sim *s = x->sim;
    for (int l = 0; l < SMK_W; l++) {
        k->lox[l] = x->reach_lo[0];
        k->loy[l] = x->reach_lo[1];
        k->loz[l] = x->reach_lo[2];
        k->hix[l] = x->reach_hi[0];
        k->hiy[l] = x->reach_hi[1];
        k->hiz[l] = x->reach_hi[2];
        k->vh[l] = s->h;
        k->vhm[l] = s->hm;
        k->vinv[l] = s->inv_den;
        k->vmgx[l] = s->mg[0];
        k->vmgy[l] = s->mg[1];
        k->vmgz[l] = s->mg[2];
        k->vwx[l] = x->wind[0];
        k->vwy[l] = x->wind[1];
        k->vwz[l] = x->wind[2];
        for (int d = 0; d < 18; d++) {
            k->vk[d][l] = s->k[d];
            k->vl[d][l] = s->len[d];
            k->vlmin[d][l] = s->lmin[d];
        }
    }
}

/* Steps the vector of nodes from cell c, `lanes` of them in the row's
 * span (the rest are computed and not stored: the next cells belong to
 * another row, maybe another thread's). True when a probe may reach one
 * of their new positions. */
SMK_ATTR static inline __attribute__((always_inline)) bool SMK_CAT(step_vec_, SMK_W)(const sm_step_ctx *x, const SMK_CAT(smk_step_k, SMK_W) *k,
                                                       size_t c, size_t lanes)
{
    const sm_sim *s = x->sim;
    const float *restrict act = s->act, *restrict surf = s->surf;
    const float *restrict px = s->pos[0], *restrict py = s->pos[1], *restrict pz = s->pos[2];
    float *restrict nx = s->next[0], *restrict ny = s->next[1], *restrict nz = s->next[2];
    float *restrict vx = s->vel[0], *restrict vy = s->vel[1], *restrict vz = s->vel[2];
    SMK_V a, X, Y, Z, VX, VY, VZ, S;
    memcpy(&a, act + c, sizeof a);
    memcpy(&S, surf + c, sizeof S);
    memcpy(&X, px + c, sizeof X);
    memcpy(&Y, py + c, sizeof Y);
    memcpy(&Z, pz + c, sizeof Z);
    memcpy(&VX, vx + c, sizeof VX);
    memcpy(&VY, vy + c, sizeof VY);
    memcpy(&VZ, vz + c, sizeof VZ);
    SMK_V FX = {0}, FY = {0}, FZ = {0};
    for (int d = 0; d < 18; d++) {
        const size_t n = (size_t)((ptrdiff_t)c + s->off[d]);
        SMK_V an, xn, yn, zn;
        memcpy(&an, act + n, sizeof an);
        memcpy(&xn, px + n, sizeof xn);
        memcpy(&yn, py + n, sizeof yn);
        memcpy(&zn, pz + n, sizeof zn);
        SMK_V dx = xn - X, dy = yn - Y, dz = zn - Z;
        SMK_V L = SMK_SQRT(dx * dx + dy * dy + dz * dz);
        SMK_I big = L > k->vlmin[d];
        SMK_V Lc = (SMK_V)((big & (SMK_I)L) | (~big & (SMK_I)k->vlmin[d]));
        SMK_V sp = (a * an * k->vk[d]) * (L - k->vl[d]) / Lc;
        FX += sp * dx;
        FY += sp * dy;
        FZ += sp * dz;
    }
    FX += a * k->vmgx + S * k->vwx;
    FY += a * k->vmgy + S * k->vwy;
    FZ += a * k->vmgz + S * k->vwz;
    VX = (VX + k->vhm * FX) * k->vinv;
    VY = (VY + k->vhm * FY) * k->vinv;
    VZ = (VZ + k->vhm * FZ) * k->vinv;
    SMK_V NX = X + k->vh * VX, NY = Y + k->vh * VY, NZ = Z + k->vh * VZ;
    SMK_I reached = (NX >= k->lox) & (NX <= k->hix) & (NY >= k->loy) & (NY <= k->hiy) & (NZ >= k->loz) &
                    (NZ <= k->hiz);
    if (lanes == (size_t)SMK_W) {
        memcpy(vx + c, &VX, sizeof VX);
        memcpy(vy + c, &VY, sizeof VY);
        memcpy(vz + c, &VZ, sizeof VZ);
        memcpy(nx + c, &NX, sizeof NX);
        memcpy(ny + c, &NY, sizeof NY);
        memcpy(nz + c, &NZ, sizeof NZ);
    } else {
        for (size_t l = 0; l < lanes; l++) {
            vx[c + l] = VX[l];
            vy[c + l] = VY[l];
            vz[c + l] = VZ[l];
            nx[c + l] = NX[l];
            ny[c + l] = NY[l];
            nz[c + l] = NZ[l];
        }
    }
    bool any = false;
    for (size_t l = 0; l < lanes; l++)
        any |= reached[l] != 0;
    return any;
}

/* A row's nodes in vectors of SMK_W lanes; a last part of at most
 * SMK_TAIL_W nodes (when defined) in a vector of that many (a row of 17
 * nodes: 8 + 8 + 4 lanes, not 8 + 8 + 8: rows are short and every lane
 * costs 18 square roots and divisions; any width gives the same bits). */
SMK_ATTR static void SMK_NAME(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    const sm_step_ctx *x = ctx;
    const sm_sim *s = x->sim;
    SMK_CAT(smk_step_k, SMK_W) k;
    SMK_CAT(step_consts_, SMK_W)(x, &k);
#ifdef SMK_TAIL_W
    SMK_CAT(smk_step_k, SMK_TAIL_W) tail;
    SMK_CAT(step_consts_, SMK_TAIL_W)(x, &tail);
#endif
    for (size_t r = begin; r < end; r++) {
        const size_t b = s->span_begin[r], e = s->span_end[r];
        bool reached = false; /* a probe may reach a new position */
        for (size_t c = b; c < e; c += SMK_W) {
            size_t lanes = e - c < (size_t)SMK_W ? e - c : (size_t)SMK_W;
#ifdef SMK_TAIL_W
            if (lanes <= SMK_TAIL_W) {
                reached |= SMK_CAT(step_vec_, SMK_TAIL_W)(x, &tail, c, lanes);
                break;
            }
#endif
            reached |= SMK_CAT(step_vec_, SMK_W)(x, &k, c, lanes);
        }
        if (x->constrain && (reached || s->span_pinned[r]))
            constrain_row(x->constrain, r);
    }
}

/* Stores v at p, all lanes, or only the first `lanes` (the end of a row:
 * the next cells belong to another row, maybe another thread's). */
#define SMK_STORE(p, v, lanes)                                                                     \
    do {                                                                                           \
        if ((lanes) == (size_t)SMK_W)                                                              \
            memcpy((p), &(v), sizeof(v));                                                          \
        else                                                                                       \
            for (size_t l_ = 0; l_ < (lanes); l_++)                                                \
                (p)[l_] = (v)[l_];                                                                 \
    } while (0)

/* a ? b : c per lane, on the lanes' bits (no rounding) */
#define SMK_SELECT(mask, b, c) ((SMK_V)(((mask) & (SMK_I)(b)) | (~(mask) & (SMK_I)(c))))

SMK_ATTR static void SMK_MEASURE(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    sm_sim *s = ctx;
    const float *restrict act = s->act;
    const float *restrict px = s->pos[0], *restrict py = s->pos[1], *restrict pz = s->pos[2];
    SMK_V vk[18], vl[18], vlmin[18], vil[18], zero = {0}, one, quarter, half_m, half_h, vmgx, vmgy, vmgz, vmax;
    for (int l = 0; l < SMK_W; l++) {
        for (int d = 0; d < 18; d++) {
            vk[d][l] = s->k[d];
            vl[d][l] = s->len[d];
            vlmin[d][l] = s->lmin[d];
            vil[d][l] = (float)s->inv_len[d];
        }
        one[l] = 1.0f;
        quarter[l] = 0.25f;
        half_m[l] = 0.5f * s->p->mass;
        half_h[l] = 0.5f * s->h;
        vmgx[l] = s->mg[0];
        vmgy[l] = s->mg[1];
        vmgz[l] = s->mg[2];
        vmax[l] = (float)MR_MAX_COORDINATE;
    }
    for (size_t r = begin; r < end; r++) {
        const size_t b = s->span_begin[r], e = s->span_end[r];
        for (size_t c = b; c < e; c += SMK_W) {
            size_t lanes = e - c < (size_t)SMK_W ? e - c : (size_t)SMK_W;
            SMK_V a, X, Y, Z;
            memcpy(&a, act + c, sizeof a);
            memcpy(&X, px + c, sizeof X);
            memcpy(&Y, py + c, sizeof Y);
            memcpy(&Z, pz + c, sizeof Z);
            SMK_V FX = vmgx, FY = vmgy, FZ = vmgz, UX = zero, UY = zero, UZ = zero;
            SMK_V S0 = zero, S1 = zero, S2 = zero, S3 = zero, S4 = zero, S5 = zero, TR = zero, VS = zero,
                  STRAIN = zero;
            for (int d = 0; d < 18; d++) {
                const size_t n = (size_t)((ptrdiff_t)c + s->off[d]);
                SMK_V an, xn, yn, zn;
                memcpy(&an, act + n, sizeof an);
                memcpy(&xn, px + n, sizeof xn);
                memcpy(&yn, py + n, sizeof yn);
                memcpy(&zn, pz + n, sizeof zn);
                SMK_V m = a * an;
                SMK_V dx = xn - X, dy = yn - Y, dz = zn - Z;
                SMK_V L = SMK_SQRT(dx * dx + dy * dy + dz * dz);
                SMK_V Lc = SMK_SELECT(L > vlmin[d], L, vlmin[d]);
                SMK_V inv = m / Lc; /* 0 where the neighbour is no node */
                SMK_V stretch = L - vl[d];
                SMK_V sp = vk[d] * stretch * inv;
                SMK_V ux = dx * inv, uy = dy * inv, uz = dz * inv;
                FX += sp * dx;
                FY += sp * dy;
                FZ += sp * dz;
                UX += ux;
                UY += uy;
                UZ += uz;
                /* the node's stiffness: sum k u u^T along the springs, plus the
                 * transverse k (1 - l / |d|) of stretched ones (sim.h) */
                S0 += vk[d] * ux * ux;
                S1 += vk[d] * uy * uy;
                S2 += vk[d] * uz * uz;
                S3 += vk[d] * ux * uy;
                S4 += vk[d] * ux * uz;
                S5 += vk[d] * uy * uz;
                SMK_V tv = m - vl[d] * inv;
                TR += vk[d] * SMK_SELECT(tv > zero, tv, zero);
                VS += quarter * vk[d] * (stretch * stretch) * m; /* each spring from both ends */
                SMK_V strain = L * vil[d] - one;
                strain = SMK_SELECT(strain < zero, -strain, strain) * m;
                STRAIN = SMK_SELECT(strain > STRAIN, strain, STRAIN);
            }
            SMK_V VX, VY, VZ, RX, RY, RZ;
            memcpy(&VX, s->vel[0] + c, sizeof VX);
            memcpy(&VY, s->vel[1] + c, sizeof VY);
            memcpy(&VZ, s->vel[2] + c, sizeof VZ);
            memcpy(&RX, s->rest[0] + c, sizeof RX);
            memcpy(&RY, s->rest[1] + c, sizeof RY);
            memcpy(&RZ, s->rest[2] + c, sizeof RZ);
            /* q + 2 p bounds the largest eigenvalue of S (sim.h) */
            SMK_V third = one / (one + one + one);
            SMK_V q = (S0 + S1 + S2) * third;
            SMK_V p2 = (S0 - q) * (S0 - q) + (S1 - q) * (S1 - q) + (S2 - q) * (S2 - q) +
                       (one + one) * (S3 * S3 + S4 * S4 + S5 * S5);
            SMK_V bound = (q + (one + one) * SMK_SQRT(p2 * (third * (one / (one + one))))) + TR;
            SMK_V kin = half_m * (VX * VX + VY * VY + VZ * VZ) * a;
            SMK_V grav = -(vmgx * (X - RX) + vmgy * (Y - RY) + vmgz * (Z - RZ)) * a;
            SMK_V shadow = half_h * (VX * FX + VY * FY + VZ * FZ) * a;
            SMK_V ax = SMK_SELECT(X < zero, -X, X), ay = SMK_SELECT(Y < zero, -Y, Y), az = SMK_SELECT(Z < zero, -Z, Z);
            SMK_I ok = (ax <= vmax) & (ay <= vmax) & (az <= vmax);
            SMK_V bad = SMK_SELECT(ok, zero, one) * a;
            /* eq. 3: the sum of unit vectors from the neighbours to the node */
            SMK_V len = SMK_SQRT(UX * UX + UY * UY + UZ * UZ);
            SMK_I some = len > zero;
            SMK_V il = SMK_SELECT(some, one / SMK_SELECT(some, len, one), zero);
            SMK_V NX = -UX * il, NY = -UY * il, NZ = -UZ * il;
            SMK_STORE(s->nstr + c, len, lanes);
            SMK_STORE(s->nrm[0] + c, NX, lanes);
            SMK_STORE(s->nrm[1] + c, NY, lanes);
            SMK_STORE(s->nrm[2] + c, NZ, lanes);
            SMK_STORE(s->cell_kinetic + c, kin, lanes);
            SMK_STORE(s->cell_spring + c, VS, lanes);
            SMK_STORE(s->cell_gravity + c, grav, lanes);
            SMK_STORE(s->cell_shadow + c, shadow, lanes);
            SMK_STORE(s->cell_strain + c, STRAIN, lanes);
            SMK_STORE(s->cell_bound + c, bound, lanes);
            SMK_STORE(s->cell_bad + c, bad, lanes);
            /* the cell this node is the low corner of, when all 8 corners are
             * nodes: inverted if a corner's three edges span no positive
             * volume (the corner's sign flips with each high side) */
            {
                const ptrdiff_t oy = (ptrdiff_t)s->grid.n[0], oz = oy * (ptrdiff_t)s->grid.n[1];
                const ptrdiff_t co[8] = {0, 1, oy, oy + 1, oz, oz + 1, oz + oy, oz + oy + 1};
                SMK_V P[8][3], all = a;
                for (int k = 1; k < 8; k++) {
                    SMK_V ak;
                    memcpy(&ak, act + c + co[k], sizeof ak);
                    all = all * ak;
                }
                bool any_cell = false;
                for (size_t l = 0; l < lanes; l++)
                    any_cell |= all[l] != 0;
                if (!any_cell) { /* no cell of 8 nodes here: none inverted */
                    SMK_STORE(s->cell_inv + c, zero, lanes);
                    continue;
                }
                for (int k = 0; k < 8; k++) {
                    memcpy(&P[k][0], px + c + co[k], sizeof P[k][0]);
                    memcpy(&P[k][1], py + c + co[k], sizeof P[k][1]);
                    memcpy(&P[k][2], pz + c + co[k], sizeof P[k][2]);
                }
                SMK_I inverted = {0};
                for (int k = 0; k < 8; k++) {
                    int bx = k & 1, by = (k >> 1) & 1, bz = k >> 2;
                    const SMK_V *o = P[k], *ex = P[k ^ 1], *ey = P[k ^ 2], *ez = P[k ^ 4];
                    SMK_V e0[3], e1[3], e2[3];
                    for (int i = 0; i < 3; i++) {
                        e0[i] = ex[i] - o[i];
                        e1[i] = ey[i] - o[i];
                        e2[i] = ez[i] - o[i];
                    }
                    SMK_V det = e0[0] * (e1[1] * e2[2] - e1[2] * e2[1]) - e0[1] * (e1[0] * e2[2] - e1[2] * e2[0]) +
                                e0[2] * (e1[0] * e2[1] - e1[1] * e2[0]);
                    if ((bx + by + bz) & 1)
                        det = -det;
                    inverted |= ~(det > zero); /* not positive, or NaN */
                }
                SMK_V inv_cell = SMK_SELECT(inverted, one, zero) * all;
                SMK_STORE(s->cell_inv + c, inv_cell, lanes);
            }
        }
        measure_row_sum(s, r);
    }
}

#undef SMK_SELECT
#undef SMK_STORE
#undef SMK_V
#undef SMK_I
