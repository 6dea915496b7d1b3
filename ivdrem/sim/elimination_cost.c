/* The cost of eliminating P A P^T in the diagonal order, for the symbolic LU's ordering
 * search (ivdrem/sim/sparse_lu.py, refine_by_groups).
 *
 * A (n x n) is a CSR pattern with its diagonal stored; row i of P A P^T is row order[i] of
 * A.  Row i of L + U is row i of P A P^T together with, for every column j < i in row i of
 * L (the fill included), the strict upper part of row j of U (Gilbert and Peierls' reach);
 * eliminating row i costs, for every such j, the length of that upper part.  One pass: the
 * upper part of each finished row is kept unsorted, each column of row i is reached once.
 *
 * Equal to sparse_lu._filled_rows + sparse_lu.elimination_cost (tests/test_sparse_lu.py),
 * compiled by ivdrem._cc into the compile cache on first use (a fraction of a second; the
 * search evaluates a few hundred orders of a real arm's loop, 5 ms each).
 */
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* Writes (multiply-adds, entries of L + U) to out[0], out[1] and returns 0; returns 1 (out
 * untouched) as soon as madds_weight * madds + weight * entries exceeds cost_limit (the
 * search's cost of a step, or with madds_weight 0 the fill alone), -1 when memory runs
 * out. */
int ivdrem_elimination_cost(int64_t n, const int64_t *indptr, const int64_t *indices,
                            const int64_t *order, double madds_weight, double weight,
                            double cost_limit, int64_t *out)
{
    int status = 0;
    int64_t nnz_a = indptr[n];
    int64_t cap = 4 * nnz_a > 16 ? 4 * nnz_a : 16;
    int64_t *inv = malloc((size_t)(n > 0 ? n : 1) * sizeof(int64_t));
    int64_t *up_ptr = calloc((size_t)n + 1, sizeof(int64_t));
    int64_t *mark = malloc((size_t)(n > 0 ? n : 1) * sizeof(int64_t));
    int64_t *row = malloc((size_t)(n > 0 ? n : 1) * sizeof(int64_t));
    int64_t *stack = malloc((size_t)(n > 0 ? n : 1) * sizeof(int64_t));
    int64_t *up = malloc((size_t)cap * sizeof(int64_t));
    int64_t madds = 0, nnz = 0;
    if (!inv || !up_ptr || !mark || !row || !stack || !up) {
        status = -1;
        goto done;
    }
    for (int64_t i = 0; i < n; i++) {
        inv[order[i]] = i;
        mark[i] = -1;
    }
    for (int64_t i = 0; i < n; i++) {
        /* the row of A, then the row of U of every column of L reached (each once) */
        int64_t lo = indptr[order[i]], hi = indptr[order[i] + 1];
        int from_a = 1;
        int64_t cnt = 0, top = 0;
        for (;;) {
            for (int64_t q = lo; q < hi; q++) {
                int64_t c = from_a ? inv[indices[q]] : up[q];
                if (mark[c] != i) {
                    mark[c] = i;
                    row[cnt++] = c;
                    if (c < i)
                        stack[top++] = c;
                }
            }
            if (top == 0)
                break;
            int64_t j = stack[--top];
            lo = up_ptr[j];
            hi = up_ptr[j + 1];
            from_a = 0;
            madds += hi - lo;
        }
        if (up_ptr[i] + cnt > cap) {
            int64_t grown_cap = 2 * cap + cnt;
            int64_t *grown = realloc(up, (size_t)grown_cap * sizeof(int64_t));
            if (!grown) {
                status = -1;
                goto done;
            }
            up = grown;
            cap = grown_cap;
        }
        int64_t m = up_ptr[i];
        for (int64_t t = 0; t < cnt; t++)
            if (row[t] > i)
                up[m++] = row[t];
        up_ptr[i + 1] = m;
        nnz += cnt;
        if (madds_weight * (double)madds + weight * (double)nnz > cost_limit) {
            status = 1;
            goto done;
        }
    }
    out[0] = madds;
    out[1] = nnz;
done:
    free(inv);
    free(up_ptr);
    free(mark);
    free(row);
    free(stack);
    free(up);
    return status;
}
