/* Runs of a counting sort (common/sort.cl, mpm/p2g_gather.cl): each key's elements land in
 * its run in the order their atomics returned; sort_run puts a run in increasing index, the
 * order a sequential counting sort gives. */
#ifndef CLFLOW_RUNS_H
#define CLFLOW_RUNS_H

/* order[begin .. end) sorted increasing in place (insertion sort: a run of the keys it is
 * made for, grid cells, holds a few elements). */
inline void sort_run(__global int *order, const int begin, const int end)
{
    for (int i = begin + 1; i < end; ++i) {
        const int v = order[i];
        int j = i - 1;
        while (j >= begin && order[j] > v) {
            order[j + 1] = order[j];
            --j;
        }
        order[j + 1] = v;
    }
}

#endif /* CLFLOW_RUNS_H */
