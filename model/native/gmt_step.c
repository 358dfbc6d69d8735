/* One incremental step of a `window` GMT (model/gmt.py, GMT.step) for a batch of sessions, in plain C.
 *
 * Why: the torch step is ~130 small operations, each 5-20 us through the dispatcher on a small CPU, so one
 * session's act cost milliseconds for ~4 MFLOP of arithmetic. This file does the same arithmetic in one call.
 *
 * Batch invariance by construction: every output element of every product is one sequential fused
 * multiply-add chain over the reduction index, started at zero, whatever the batch size or the blocking, and
 * every other operation is per row. A row's result therefore never depends on which other rows share the call
 * (batched and unbatched answers agree bit for bit), and agrees with torch's step to float rounding.
 *
 * Layouts (float32, row-major, contiguous): every weight matrix is given transposed, [in, out], and packed in
 * column tiles of NB (see `linear`; model/native/__init__.py `pack`); the key/value
 * caches are [n_layer, n_slots, n_head, W, d] and `tok` is [n_slots, W] (model/kv_cache.py).
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

typedef struct {
    int64_t n_embd, n_head, n_layer, obs_dim, act_dim, discrete, n_goals, max_timestep, context_length;
    const float *goal_emb;             /* [n_goals + 1, C] */
    const float *state_w, *state_b;    /* [obs_dim, C], [C] (unused when state embeddings are given) */
    const float *action_w, *action_b;  /* [act_dim, C], [C]; discrete: action_w is the table [act_dim, C] */
    const float *time_emb;             /* [max_timestep, C] */
    const float *ln_in_w, *ln_in_b;
    const float *const *ln1_w, *const *ln1_b, *const *qkv_w, *const *qkv_b, *const *proj_w, *const *proj_b;
    const float *const *ln2_w, *const *ln2_b, *const *fc_w, *const *fc_b, *const *out_w, *const *out_b;
    const float *ln_f_w, *ln_f_b, *head_w, *head_b; /* action head [C, act_dim], [act_dim] */
    /* The blocks' four matrices as bfloat16 pairs (`linear_bf16`), or NULL: the fp32 products above. */
    const uint32_t *const *qkv_wb, *const *proj_wb, *const *fc_wb, *const *out_wb;
} Model;

#define NB 32 /* output columns per tile (must match model/native/__init__.py TILE) */
#define MB 8  /* rows per tile: 8 x NB / 16 = 16 vector accumulators */

/* y[m, n0:n0+nb] = b + x[m, :] . w[:, n] for up to MB rows; `wt` is the packed tile [K, NB]. */
static inline __attribute__((always_inline)) void tile(const float *x, int64_t K, const float *wt, int64_t N,
                                                       const float *b, float *y, int64_t n0, int mb, int nb) {
    float acc[MB][NB];
    for (int r = 0; r < mb; r++)
        for (int j = 0; j < NB; j++) acc[r][j] = 0.0f;
    for (int64_t k = 0; k < K; k++) {
        const float *wk = wt + k * NB;
        for (int r = 0; r < mb; r++) {
            float xv = x[r * K + k];
            for (int j = 0; j < NB; j++) acc[r][j] = fmaf(xv, wk[j], acc[r][j]);
        }
    }
    for (int r = 0; r < mb; r++)
        for (int j = 0; j < nb; j++) y[r * N + n0 + j] = acc[r][j] + (b ? b[n0 + j] : 0.0f);
}

/* TILE(m, mb) for each block of MB rows of M, then once for the last M % MB rows: every call has a constant
 * row count, so each tile's loops unroll. */
#define FOR_ROW_BLOCKS(M, TILE)                                                                               \
    do {                                                                                                       \
        int64_t m_ = 0;                                                                                        \
        for (; m_ + MB <= (M); m_ += MB) TILE(m_, MB);                                                         \
        switch ((M) - m_) {                                                                                    \
        case 7: TILE(m_, 7); break;                                                                            \
        case 6: TILE(m_, 6); break;                                                                            \
        case 5: TILE(m_, 5); break;                                                                            \
        case 4: TILE(m_, 4); break;                                                                            \
        case 3: TILE(m_, 3); break;                                                                            \
        case 2: TILE(m_, 2); break;                                                                            \
        case 1: TILE(m_, 1); break;                                                                            \
        }                                                                                                      \
    } while (0)

/* y [M, N] = x [M, K] @ w [K, N] + b, with w packed as ceil(N / NB) tiles [K, NB] (zero-padded columns):
 * each tile is read front to back, once per block of MB rows. */
static void linear(const float *x, int64_t M, int64_t K, const float *w, const float *b, int64_t N, float *y) {
    for (int64_t n0 = 0; n0 < N; n0 += NB) {
        const int nb = (int)(N - n0 < NB ? N - n0 : NB);
        const float *wt = w + n0 * K; /* tile n0 / NB starts at (n0 / NB) * K * NB */
#define T(m, mb) tile(x + (m) * K, K, wt, N, b, y + (m) * N, n0, mb, nb)
        FOR_ROW_BLOCKS(M, T);
#undef T
    }
}

#if defined(__AVX512BF16__) && defined(__AVX512F__)
#include <immintrin.h>
#define GMT_BF16 1
#else
#define GMT_BF16 0
#endif

/* Whether this build has the bfloat16 products (the CPU's AVX-512 BF16 `vdpbf16ps`). */
int gmt_bf16(void) { return GMT_BF16; }

#if GMT_BF16
/* f as bfloat16, rounded to nearest even, denormals flushed to zero (as `vcvtne2ps2bf16`). */
static inline uint32_t bf16_of(float f) {
    uint32_t u;
    memcpy(&u, &f, sizeof u);
    if ((u & 0x7f800000u) == 0) return (u >> 16) & 0x8000u;             /* zero or denormal: signed zero */
    if ((u & 0x7fffffffu) > 0x7f800000u) return ((u >> 16) | 0x40u) & 0xffffu; /* NaN stays NaN */
    return ((u + 0x7fffu + ((u >> 16) & 1u)) >> 16) & 0xffffu;
}

/* xb [M, K / 2] = the rows of x [M, K] (K even) as bfloat16 pairs: element k in the low half, k + 1 in the high. */
static void to_bf16_pairs(const float *x, int64_t M, int64_t K, uint32_t *xb) {
    for (int64_t m = 0; m < M; m++) {
        const float *r = x + m * K;
        uint32_t *o = xb + m * (K / 2);
        int64_t k = 0;
        for (; k + 32 <= K; k += 32) {
            __m512bh v = _mm512_cvtne2ps_pbh(_mm512_loadu_ps(r + k + 16), _mm512_loadu_ps(r + k));
            _mm512_storeu_si512(o + k / 2, (__m512i)v);
        }
        for (; k < K; k += 2) o[k / 2] = bf16_of(r[k]) | (bf16_of(r[k + 1]) << 16);
    }
}

/* `tile` in bfloat16: wt is the packed tile [K / 2, NB] of weight pairs, xb the rows' pairs; each output is
 * one sequential chain of `vdpbf16ps` (two products and a sum per step, fp32 accumulation), whatever the batch. */
static inline __attribute__((always_inline)) void tile_bf16(const uint32_t *xb, int64_t K2, const uint32_t *wt,
                                                            int64_t N, const float *b, float *y, int64_t n0, int mb,
                                                            int nb) {
    __m512 acc[MB][2];
    for (int r = 0; r < mb; r++) acc[r][0] = acc[r][1] = _mm512_setzero_ps();
    for (int64_t k = 0; k < K2; k++) {
        const __m512bh w0 = (__m512bh)_mm512_loadu_si512(wt + k * NB);
        const __m512bh w1 = (__m512bh)_mm512_loadu_si512(wt + k * NB + 16);
        for (int r = 0; r < mb; r++) {
            const __m512bh xv = (__m512bh)_mm512_set1_epi32((int)xb[r * K2 + k]);
            acc[r][0] = _mm512_dpbf16_ps(acc[r][0], xv, w0);
            acc[r][1] = _mm512_dpbf16_ps(acc[r][1], xv, w1);
        }
    }
    for (int r = 0; r < mb; r++) {
        float o[NB];
        _mm512_storeu_ps(o, acc[r][0]);
        _mm512_storeu_ps(o + 16, acc[r][1]);
        for (int j = 0; j < nb; j++) y[r * N + n0 + j] = o[j] + (b ? b[n0 + j] : 0.0f);
    }
}

/* `linear` with x rounded to bfloat16 (into `xb`, [M, K / 2]) and w packed as ceil(N / NB) tiles [K / 2, NB] of
 * bfloat16 pairs (model/native/__init__.py `pack_bf16`). */
static void linear_bf16(const float *x, int64_t M, int64_t K, const uint32_t *w, const float *b, int64_t N,
                        float *y, uint32_t *xb) {
    const int64_t K2 = K / 2;
    to_bf16_pairs(x, M, K, xb);
    for (int64_t n0 = 0; n0 < N; n0 += NB) {
        const int nb = (int)(N - n0 < NB ? N - n0 : NB);
        const uint32_t *wt = w + n0 * K2;
#define T(m, mb) tile_bf16(xb + (m) * K2, K2, wt, N, b, y + (m) * N, n0, mb, nb)
        FOR_ROW_BLOCKS(M, T);
#undef T
    }
}
#endif

/* One of a block's four products: in bfloat16 where the model has them (`wb`), else in fp32. */
static void block_linear(const float *const *w, const uint32_t *const *wb, int64_t l, const float *x, int64_t M,
                         int64_t K, const float *b, int64_t N, float *y, uint32_t *xb) {
#if GMT_BF16
    if (wb) {
        linear_bf16(x, M, K, wb[l], b, N, y, xb);
        return;
    }
#else
    (void)wb, (void)xb;
#endif
    linear(x, M, K, w[l], b, N, y);
}

/* y [M, N] = x [M, K] @ w + b as the step computes a block's product: w packed by `pack` (fp32) or, with `bf16`,
 * by `pack_bf16` (K even). Returns -1 where bf16 is asked of a build without it or scratch cannot be had. For tests. */
int gmt_linear(const float *x, int64_t M, int64_t K, const void *w, const float *b, int64_t N, float *y, int bf16) {
#if GMT_BF16
    if (bf16) {
        uint32_t *xb = malloc(sizeof(uint32_t) * (M * K / 2 + 1));
        if (!xb) return -1;
        linear_bf16(x, M, K, (const uint32_t *)w, b, N, y, xb);
        free(xb);
        return 0;
    }
#else
    if (bf16) return -1;
#endif
    linear(x, M, K, (const float *)w, b, N, y);
    return 0;
}

/* Sum of a[0:n] with 8 fixed lanes (vectorisable without reassociation). */
static float sum8(const float *a, int64_t n) {
    float l[8] = {0, 0, 0, 0, 0, 0, 0, 0};
    int64_t i = 0;
    for (; i + 8 <= n; i += 8)
        for (int j = 0; j < 8; j++) l[j] += a[i + j];
    float s = ((l[0] + l[1]) + (l[2] + l[3])) + ((l[4] + l[5]) + (l[6] + l[7]));
    for (; i < n; i++) s += a[i];
    return s;
}

typedef float v16 __attribute__((vector_size(64)));
typedef float v16u __attribute__((vector_size(64), aligned(4))); /* unaligned loads and stores */

/* Sum of the 16 lanes, in a fixed tree order. */
static inline float hsum16(v16 a) {
    v16 b = a + __builtin_shufflevector(a, a, 8, 9, 10, 11, 12, 13, 14, 15, 0, 1, 2, 3, 4, 5, 6, 7);
    b = b + __builtin_shufflevector(b, b, 4, 5, 6, 7, 0, 1, 2, 3, 12, 13, 14, 15, 8, 9, 10, 11);
    b = b + __builtin_shufflevector(b, b, 2, 3, 0, 1, 6, 7, 4, 5, 10, 11, 8, 9, 14, 15, 12, 13);
    return b[0] + b[1];
}

/* a . b over n values (16 lanes, then a fixed tree, then the tail). */
static inline float dot16(const float *a, const float *b, int64_t n) {
    v16 acc = {0};
    int64_t i = 0;
    for (; i + 16 <= n; i += 16) acc += *(const v16u *)(a + i) * *(const v16u *)(b + i);
    float s = hsum16(acc);
    for (; i < n; i++) s = fmaf(a[i], b[i], s);
    return s;
}

typedef int32_t v16i __attribute__((vector_size(64)));

static inline v16 select16(v16i mask, v16 a, v16 b) { /* mask ? a : b, lane-wise */
    return (v16)(((v16i)a & mask) | ((v16i)b & ~mask));
}

/* exp(x) lane-wise (Cephes expf: range reduction by ln 2 and a degree-6 polynomial, ~1 ulp; inputs are
 * clamped to [-87, 88], so exp(-inf) gives ~1.6e-38, i.e. 0 after any sum with a normal value). */
static inline v16 vexp(v16 x) {
    const v16 lo = (v16){0} - 87.0f, hi = (v16){0} + 88.0f;
    x = select16(x < lo, lo, x);
    x = select16(x > hi, hi, x);
    v16 t = x * 1.44269504088896341f + 0.5f;
    v16i ni = __builtin_convertvector(t, v16i); /* truncation: floor needs one less where it rounded up */
    ni += (v16i)(__builtin_convertvector(ni, v16) > t);
    v16 n = __builtin_convertvector(ni, v16);
    v16 r = x - n * 0.693359375f + n * 2.12194440e-4f;
    v16 p = (v16){0} + 1.9875691500e-4f;
    p = p * r + 1.3981999507e-3f;
    p = p * r + 8.3334519073e-3f;
    p = p * r + 4.1665795894e-2f;
    p = p * r + 1.6666665459e-1f;
    p = p * r + 5.0000001201e-1f;
    p = p * r * r + r + 1.0f;
    return p * (v16)((ni + 127) << 23);
}

/* GELU, tanh approximation (torch's approximate="tanh"), lane-wise; tanh(z) = 1 - 2 / (exp(2z) + 1). */
static inline v16 vgelu(v16 u) {
    v16 z = 0.7978845608028654f * (u + 0.044715f * u * u * u);
    v16 th = 1.0f - 2.0f / (vexp(2.0f * z) + 1.0f);
    return 0.5f * u * (1.0f + th);
}

/* a[i] = f(a[i] + shift) for i < n, in 16-lane chunks (the tail through a padded copy). */
#define MAP16(a, n, shift, f)                                                                                  \
    do {                                                                                                       \
        int64_t i_ = 0;                                                                                        \
        for (; i_ + 16 <= (n); i_ += 16) *(v16u *)((a) + i_) = f(*(const v16u *)((a) + i_) + (shift));          \
        if (i_ < (n)) {                                                                                        \
            float pad_[16] = {0};                                                                              \
            memcpy(pad_, (a) + i_, sizeof(float) * ((n) - i_));                                                \
            v16 r_ = f(*(const v16u *)pad_ + (shift));                                                         \
            memcpy((a) + i_, &r_, sizeof(float) * ((n) - i_));                                                 \
        }                                                                                                      \
    } while (0)

/* o[j, :D] = sum_p att[j, p] v[p, :D] for the 3 queries j (rows of o C apart), one pass over the values. */
static inline __attribute__((always_inline)) void attend_values(const float *att, const float *v, int64_t W,
                                                                int64_t D, float *o, int64_t C) {
    if (D % 16 == 0 && D <= 128) {
        v16 acc[3][8];
        for (int j = 0; j < 3; j++)
            for (int64_t c = 0; c < D / 16; c++) acc[j][c] = (v16){0};
        for (int64_t p = 0; p < W; p++) {
            const float a0 = att[p], a1 = att[W + p], a2 = att[2 * W + p];
            for (int64_t c = 0; c < D / 16; c++) {
                v16 vv = *(const v16u *)(v + p * D + 16 * c);
                acc[0][c] += a0 * vv;
                acc[1][c] += a1 * vv;
                acc[2][c] += a2 * vv;
            }
        }
        for (int j = 0; j < 3; j++)
            for (int64_t c = 0; c < D / 16; c++) *(v16u *)(o + j * C + 16 * c) = acc[j][c];
        return;
    }
    for (int j = 0; j < 3; j++)
        for (int64_t c = 0; c < D; c++) {
            float acc = 0.0f;
            for (int64_t p = 0; p < W; p++) acc = fmaf(att[j * W + p], v[p * D + c], acc);
            o[j * C + c] = acc;
        }
}

/* LayerNorm of each row of x [M, C] into y (eps 1e-5, biased variance, as torch). */
static void layer_norm(const float *x, int64_t M, int64_t C, const float *w, const float *b, float *y,
                       float *tmp) {
    for (int64_t m = 0; m < M; m++) {
        const float *r = x + m * C;
        float mean = sum8(r, C) / (float)C;
        for (int64_t i = 0; i < C; i++) tmp[i] = (r[i] - mean) * (r[i] - mean);
        float rstd = 1.0f / sqrtf(sum8(tmp, C) / (float)C + 1e-5f);
        for (int64_t i = 0; i < C; i++) y[m * C + i] = (r[i] - mean) * rstd * w[i] + b[i];
    }
}

static inline int64_t floordiv3(int64_t a) { return a >= 0 ? a / 3 : -((-a + 2) / 3); }

static inline const float *row_of(const float *table, int64_t rows, int64_t i, int64_t C) {
    if (i < 0) i = 0;
    if (i > rows - 1) i = rows - 1;
    return table + i * C;
}

/* One step for B sessions; returns 0, or -1 when scratch memory could not be allocated.
 *
 * prev_action: [B, act_dim] floats (continuous) or prev_ids [B] (discrete) of timestep t - 1 (ignored at t = 0
 *   by the caller's zeroing); goals, blend_to [B] (blend_to may be NULL), blend_w [B]; states [B, obs_dim]
 *   normalised, or state_emb [B, C] precomputed (then states is ignored); t [B]; slots [B] distinct;
 *   out [B, act_dim] (tanh for continuous, logits for discrete).
 */
int gmt_step(const Model *md, int64_t B, const float *prev_action, const int64_t *prev_ids, const int64_t *goals,
             const int64_t *blend_to, const float *blend_w, const float *states, const float *state_emb,
             const int64_t *t, const int64_t *slots, float *kc, float *vc, int64_t *tok, int64_t n_slots,
             int64_t W, float *out) {
    const int64_t C = md->n_embd, H = md->n_head, D = C / H, M = 3 * B, T = md->max_timestep;
    const int64_t Kc = md->context_length;
    const float scale = 1.0f / sqrtf((float)D);
    float *x = malloc(sizeof(float) * M * C);         /* residual stream [B, 3, C] */
    float *h = malloc(sizeof(float) * M * C);         /* normed */
    float *big = malloc(sizeof(float) * M * 4 * C);   /* qkv [M, 3C] / fc [M, 4C] */
    float *y = malloc(sizeof(float) * M * C);         /* attention output / proj */
    float *e = malloc(sizeof(float) * B * C);         /* state embeddings */
    float *att = malloc(sizeof(float) * (3 * W + C)); /* scores of 3 queries, then tmp */
    int64_t *idx = malloc(sizeof(int64_t) * M), *pos = malloc(sizeof(int64_t) * M);
    const int bf = md->qkv_wb || md->proj_wb || md->fc_wb || md->out_wb;
    uint32_t *xb = bf ? malloc(sizeof(uint32_t) * M * 2 * C) : NULL; /* rows as bf16 pairs [M, 4C / 2] */
    if (!x || !h || !big || !y || !e || !att || !idx || !pos || (bf && !xb)) {
        free(x), free(h), free(big), free(y), free(e), free(att), free(idx), free(pos), free(xb);
        return -1;
    }
    float *tmp = att + 3 * W;

    /* Embeddings: a_{t-1}, g_t, s_t (+ timestep embeddings), then ln_in. */
    if (state_emb) {
        memcpy(e, state_emb, sizeof(float) * B * C);
    } else {
        linear(states, B, md->obs_dim, md->state_w, md->state_b, C, e);
    }
    if (!md->discrete) linear(prev_action, B, md->act_dim, md->action_w, md->action_b, C, y); /* [B, C] */
    for (int64_t r = 0; r < B; r++) {
        const float *te = row_of(md->time_emb, T, t[r], C), *tpe = row_of(md->time_emb, T, t[r] - 1, C);
        const float *ae = md->discrete ? md->action_w + prev_ids[r] * C : y + r * C;
        const float *g0 = md->goal_emb + goals[r] * C;
        float *xa = x + (3 * r) * C, *xg = xa + C, *xs = xg + C;
        for (int64_t i = 0; i < C; i++) xa[i] = ae[i] + tpe[i];
        if (blend_to && blend_w[r] != 0.0f) {
            const float *g1 = md->goal_emb + blend_to[r] * C;
            float w = blend_w[r];
            for (int64_t i = 0; i < C; i++) {
                float d = g1[i] - g0[i]; /* torch.lerp */
                xg[i] = (w < 0.5f ? g0[i] + w * d : g1[i] - d * (1.0f - w)) + te[i];
            }
        } else {
            for (int64_t i = 0; i < C; i++) xg[i] = g0[i] + te[i];
        }
        for (int64_t i = 0; i < C; i++) xs[i] = e[r * C + i] + te[i];
        for (int j = 0; j < 3; j++) {
            int64_t n = 3 * t[r] - 1 + j;
            idx[3 * r + j] = n;
            pos[3 * r + j] = ((n % W) + W) % W;
            tok[slots[r] * W + pos[3 * r + j]] = n < 0 ? -1 : n;
        }
    }
    layer_norm(x, M, C, md->ln_in_w, md->ln_in_b, x, tmp);

    for (int64_t l = 0; l < md->n_layer; l++) {
        layer_norm(x, M, C, md->ln1_w[l], md->ln1_b[l], h, tmp);
        block_linear(md->qkv_w, md->qkv_wb, l, h, M, C, md->qkv_b[l], 3 * C, big, xb); /* [M, 3C]: q | k | v */
        for (int64_t r = 0; r < B; r++) {
            const int64_t *tk = tok + slots[r] * W;
            for (int64_t hd = 0; hd < H; hd++) {
                /* cache block of (layer, slot, head): [W, D] */
                float *kb = kc + ((l * n_slots + slots[r]) * H + hd) * W * D;
                float *vb = vc + ((l * n_slots + slots[r]) * H + hd) * W * D;
                for (int j = 0; j < 3; j++) {
                    const float *q = big + (3 * r + j) * 3 * C;
                    memcpy(kb + pos[3 * r + j] * D, q + C + hd * D, sizeof(float) * D);
                    memcpy(vb + pos[3 * r + j] * D, q + 2 * C + hd * D, sizeof(float) * D);
                }
                const float *q0 = big + (3 * r) * 3 * C + hd * D;
                const float *qq[3] = {q0, q0 + 3 * C, q0 + 6 * C};
                float mx[3] = {-INFINITY, -INFINITY, -INFINITY}, sum[3] = {0, 0, 0};
                for (int64_t p = 0; p < W; p++) {
                    const int64_t kt = tk[p], ks = floordiv3(kt);
                    for (int j = 0; j < 3; j++) {
                        const int64_t qi = idx[3 * r + j];
                        int see = (kt >= 0 && kt <= qi && floordiv3(qi) - ks < Kc) || p == pos[3 * r + j];
                        float sc = see ? dot16(qq[j], kb + p * D, D) * scale : -INFINITY;
                        att[j * W + p] = sc;
                        if (sc > mx[j]) mx[j] = sc;
                    }
                }
                for (int j = 0; j < 3; j++) {
                    float *aj = att + j * W;
                    MAP16(aj, W, -mx[j], vexp);
                    sum[j] = sum8(aj, W);
                    for (int64_t p = 0; p < W; p++) aj[p] /= sum[j];
                }
                float *o0 = y + (3 * r) * C + hd * D;
                switch (D) { /* constant widths keep the 3 x D/16 accumulators in registers */
                case 128: attend_values(att, vb, W, 128, o0, C); break;
                case 64: attend_values(att, vb, W, 64, o0, C); break;
                case 32: attend_values(att, vb, W, 32, o0, C); break;
                case 16: attend_values(att, vb, W, 16, o0, C); break;
                default: attend_values(att, vb, W, D, o0, C);
                }
            }
        }
        block_linear(md->proj_w, md->proj_wb, l, y, M, C, md->proj_b[l], C, h, xb);
        for (int64_t i = 0; i < M * C; i++) x[i] += h[i];
        layer_norm(x, M, C, md->ln2_w[l], md->ln2_b[l], h, tmp);
        block_linear(md->fc_w, md->fc_wb, l, h, M, C, md->fc_b[l], 4 * C, big, xb);
        MAP16(big, M * 4 * C, 0.0f, vgelu);
        block_linear(md->out_w, md->out_wb, l, big, M, 4 * C, md->out_b[l], C, h, xb);
        for (int64_t i = 0; i < M * C; i++) x[i] += h[i];
    }
    /* Heads at the state token only. */
    for (int64_t r = 0; r < B; r++) memcpy(y + r * C, x + (3 * r + 2) * C, sizeof(float) * C);
    layer_norm(y, B, C, md->ln_f_w, md->ln_f_b, h, tmp);
    linear(h, B, C, md->head_w, md->head_b, md->act_dim, out);
    if (!md->discrete)
        for (int64_t i = 0; i < B * md->act_dim; i++) out[i] = tanhf(out[i]); /* exact libm tanh */
    free(x), free(h), free(big), free(y), free(e), free(att), free(idx), free(pos), free(xb);
    return 0;
}

/* ----- sampling noise: model/engine.py `uniforms` / `normals`, the same splitmix64 construction ----------- */
static const uint64_t GOLDEN = 0x9E3779B97F4A7C15ull;

static inline uint64_t mix64(uint64_t x) {
    x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ull;
    x = (x ^ (x >> 27)) * 0x94D049BB133111EBull;
    return x ^ (x >> 31);
}

static inline double uniform01(uint64_t seed, uint64_t step, int64_t j, uint64_t stream) {
    uint64_t key = mix64(seed * GOLDEN + mix64(step + stream * GOLDEN));
    uint64_t bits = mix64(key + (uint64_t)(j + 1) * GOLDEN);
    return ((double)(bits >> 11) + 0.5) / 9007199254740992.0; /* 2^53 */
}

/* out [B, n]: uniforms in (0, 1) of (seed, step, stream). */
void gmt_uniforms(const uint64_t *seed, const int64_t *step, int64_t B, int64_t n, int64_t stream, double *out) {
    for (int64_t r = 0; r < B; r++)
        for (int64_t j = 0; j < n; j++) out[r * n + j] = uniform01(seed[r], (uint64_t)step[r], j, (uint64_t)stream);
}

/* out [B, n]: standard normals by Box-Muller from the uniforms of streams 1 and 2. */
void gmt_normals(const uint64_t *seed, const int64_t *step, int64_t B, int64_t n, double *out) {
    for (int64_t r = 0; r < B; r++)
        for (int64_t j = 0; j < n; j++) {
            double u1 = uniform01(seed[r], (uint64_t)step[r], j, 1), u2 = uniform01(seed[r], (uint64_t)step[r], j, 2);
            out[r * n + j] = sqrt(-2.0 * log(u1)) * cos(6.283185307179586 * u2);
        }
}

/* ----- one act of continuous-action sessions: model/engine.py `PolicyEngine._step` + `_choose` ------------ */
typedef struct { /* the engine's SessionPool arrays, indexed by slot (model/engine.py) */
    int64_t n_slots, H, sample_mode;
    int64_t *step, *goal, *blend_from, *blend_steps, *blend_done, *mode, *version;
    const uint64_t *seed;
    int64_t *h_goal, *h_blend_to;
    float *h_blend_w, *h_state, *h_action;
    const double *noise_var; /* [n_goals, act_dim] variance of `sample` noise, or NULL */
    float *kc, *vc;
    int64_t *tok, W;
} Pool;

/* For each row: the goal token and blend weight, the incremental step, the mode's noise, clipping to [-1, 1],
 * and, for the rows whose prediction is finite (ok[r] = 1), the commit of the step to the pool. `taken` [B, A]
 * gets the model-space actions. Returns 0, or -1 when scratch memory could not be allocated. */
int gmt_act(const Model *md, const Pool *pl, int64_t B, const int64_t *slots, const float *states, float *taken,
            uint8_t *ok) {
    const int64_t A = md->act_dim, obs = md->obs_dim, H = pl->H;
    int64_t *t = malloc(sizeof(int64_t) * B), *g = malloc(sizeof(int64_t) * B), *gl = malloc(sizeof(int64_t) * B);
    float *w = malloc(sizeof(float) * B), *prev = malloc(sizeof(float) * B * A), *pred = malloc(sizeof(float) * B * A);
    double *noise = malloc(sizeof(double) * A);
    if (!t || !g || !gl || !w || !prev || !pred || !noise) {
        free(t), free(g), free(gl), free(w), free(prev), free(pred), free(noise);
        return -1;
    }
    int any_blend = 0;
    for (int64_t r = 0; r < B; r++) {
        const int64_t s = slots[r];
        const int blending = pl->blend_steps[s] > pl->blend_done[s];
        t[r] = pl->step[s];
        gl[r] = pl->goal[s];
        g[r] = blending ? pl->blend_from[s] : gl[r];
        const int64_t bs = pl->blend_steps[s] > 1 ? pl->blend_steps[s] : 1;
        w[r] = blending ? (float)((double)(pl->blend_done[s] + 1) / (double)bs) : 0.0f;
        any_blend |= w[r] > 0.0f;
        const int64_t pp = ((t[r] - 1) % H + H) % H;
        for (int64_t j = 0; j < A; j++) prev[r * A + j] = t[r] == 0 ? 0.0f : pl->h_action[(s * H + pp) * A + j];
    }
    int rc = gmt_step(md, B, prev, NULL, g, any_blend ? gl : NULL, w, states, NULL, t, slots, pl->kc, pl->vc, pl->tok,
                      pl->n_slots, pl->W, pred);
    for (int64_t r = 0; rc == 0 && r < B; r++) {
        const int64_t s = slots[r];
        ok[r] = 1;
        for (int64_t j = 0; j < A; j++) ok[r] &= isfinite(pred[r * A + j]) ? 1 : 0;
        const int sample = pl->noise_var && pl->mode[s] == pl->sample_mode;
        if (sample) gmt_normals(&pl->seed[s], &t[r], 1, A, noise);
        for (int64_t j = 0; j < A; j++) {
            double a = ok[r] ? pred[r * A + j] : 0.0;
            if (sample) {
                const float omw = 1.0f - w[r]; /* float32, as numpy computes it */
                double var = (double)omw * pl->noise_var[g[r] * A + j] + (double)w[r] * pl->noise_var[gl[r] * A + j];
                a += sqrt(var) * noise[j];
            }
            taken[r * A + j] = (float)(a < -1.0 ? -1.0 : (a > 1.0 ? 1.0 : a));
        }
        if (!ok[r]) continue;
        const int64_t pos = t[r] % H;
        pl->h_goal[s * H + pos] = g[r];
        pl->h_blend_to[s * H + pos] = gl[r];
        pl->h_blend_w[s * H + pos] = w[r];
        memcpy(pl->h_state + (s * H + pos) * obs, states + r * obs, sizeof(float) * obs);
        memcpy(pl->h_action + (s * H + pos) * A, taken + r * A, sizeof(float) * A);
        pl->step[s] += 1;
        pl->version[s] += 1;
        if (pl->blend_steps[s] > pl->blend_done[s]) {
            pl->blend_done[s] += 1;
            if (pl->blend_done[s] >= pl->blend_steps[s]) {
                pl->blend_from[s] = pl->goal[s];
                pl->blend_steps[s] = pl->blend_done[s] = 0;
            }
        }
    }
    free(t), free(g), free(gl), free(w), free(prev), free(pred), free(noise);
    return rc;
}
