/*
 * sim_kernel.h - the step kernel of sim.c (force, kick and drift of every
 * node of a range of grid rows), included by sim.c once per vector width.
 * The includer defines:
 *   SMK_W      lanes per vector
 *   SMK_NAME   the function's name
 *   SMK_ATTR   function attributes (a target ISA), may be empty
 *   SMK_SQRT   vector square root (x)
 * Every lane computes exactly the operation sequence of one node, so all
 * widths give the same bits (sim.h).
 */

typedef float SMK_CAT(smk_v, SMK_W) __attribute__((vector_size(4 * SMK_W)));
typedef int32_t SMK_CAT(smk_i, SMK_W) __attribute__((vector_size(4 * SMK_W)));
#define SMK_V SMK_CAT(smk_v, SMK_W)
#define SMK_I SMK_CAT(smk_i, SMK_W)

SMK_ATTR static void SMK_NAME(void *ctx, size_t begin, size_t end, unsigned worker)
{
    (void)worker;
    const sm_step_ctx *x = ctx;
    const sm_sim *s = x->sim;
    const float *restrict act = s->act, *restrict surf = s->surf;
    const float *restrict px = s->pos[0], *restrict py = s->pos[1], *restrict pz = s->pos[2];
    float *restrict nx = s->next[0], *restrict ny = s->next[1], *restrict nz = s->next[2];
    float *restrict vx = s->vel[0], *restrict vy = s->vel[1], *restrict vz = s->vel[2];
    SMK_V vh, vhm, vinv, vmgx, vmgy, vmgz, vwx, vwy, vwz, vk[18], vl[18], vlmin[18];
    for (int l = 0; l < SMK_W; l++) {
        vh[l] = s->h;
        vhm[l] = s->hm;
        vinv[l] = s->inv_den;
        vmgx[l] = s->mg[0];
        vmgy[l] = s->mg[1];
        vmgz[l] = s->mg[2];
        vwx[l] = x->wind[0];
        vwy[l] = x->wind[1];
        vwz[l] = x->wind[2];
        for (int d = 0; d < 18; d++) {
            vk[d][l] = s->k[d];
            vl[d][l] = s->len[d];
            vlmin[d][l] = s->lmin[d];
        }
    }
    for (size_t r = begin; r < end; r++) {
        const size_t b = s->span_begin[r], e = s->span_end[r];
        for (size_t c = b; c < e; c += SMK_W) {
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
                SMK_I big = L > vlmin[d];
                SMK_V Lc = (SMK_V)((big & (SMK_I)L) | (~big & (SMK_I)vlmin[d]));
                SMK_V sp = (a * an * vk[d]) * (L - vl[d]) / Lc;
                FX += sp * dx;
                FY += sp * dy;
                FZ += sp * dz;
            }
            FX += a * vmgx + S * vwx;
            FY += a * vmgy + S * vwy;
            FZ += a * vmgz + S * vwz;
            VX = (VX + vhm * FX) * vinv;
            VY = (VY + vhm * FY) * vinv;
            VZ = (VZ + vhm * FZ) * vinv;
            SMK_V NX = X + vh * VX, NY = Y + vh * VY, NZ = Z + vh * VZ;
            /* whole vectors inside the span; the last one lane by lane, so no
             * cell of another row (another thread's) is ever written */
            size_t lanes = e - c < (size_t)SMK_W ? e - c : (size_t)SMK_W;
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
        }
    }
}

#undef SMK_V
#undef SMK_I
