/* A closed-loop Modbus TCP load client on libmodbus, for bench/bench_scale.py.
 *
 * usage: modbus_load HOST PORT UNIT CONNECTIONS SECONDS NREGS
 *
 * Each of CONNECTIONS threads opens its own connection and reads NREGS holding registers from address 0
 * of UNIT, one request outstanding at a time, for SECONDS. Prints one line:
 *   requests=<n> errors=<n> rate=<req/s> p50_us=<latency> p99_us=<latency>
 * Build: gcc -O2 -o modbus_load modbus_load.c $(pkg-config --cflags --libs libmodbus) -lpthread
 */
#include <errno.h>
#include <modbus.h>
#include <pthread.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#define MAX_SAMPLES 4000000

typedef struct {
    const char *host;
    int port, unit, nregs;
    double seconds;
    long requests, errors;
    float *lat_us; /* latencies of this thread */
    long nlat, cap;
} job_t;

static double now(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + ts.tv_nsec * 1e-9;
}

static void *run(void *arg) {
    job_t *job = arg;
    uint16_t regs[125];
    modbus_t *ctx = modbus_new_tcp(job->host, job->port);
    if (ctx == NULL || modbus_set_slave(ctx, job->unit) == -1 || modbus_connect(ctx) == -1) {
        fprintf(stderr, "connect failed: %s\n", modbus_strerror(errno));
        job->errors = -1;
        if (ctx) modbus_free(ctx);
        return NULL;
    }
    double end = now() + job->seconds;
    for (;;) {
        double t0 = now();
        if (t0 >= end) break;
        int rc = modbus_read_registers(ctx, 0, job->nregs, regs);
        double t1 = now();
        if (rc != job->nregs) {
            job->errors++;
            if (job->errors > 1000) break;
            continue;
        }
        job->requests++;
        if (job->nlat < job->cap) job->lat_us[job->nlat++] = (float)((t1 - t0) * 1e6);
    }
    modbus_close(ctx);
    modbus_free(ctx);
    return NULL;
}

static int cmp(const void *a, const void *b) {
    float x = *(const float *)a, y = *(const float *)b;
    return (x > y) - (x < y);
}

int main(int argc, char **argv) {
    if (argc != 7) {
        fprintf(stderr, "usage: %s HOST PORT UNIT CONNECTIONS SECONDS NREGS\n", argv[0]);
        return 2;
    }
    int conns = atoi(argv[4]);
    int nregs = atoi(argv[6]);
    if (conns < 1 || conns > 256 || nregs < 1 || nregs > 125) {
        fprintf(stderr, "CONNECTIONS must be 1..256 and NREGS 1..125\n");
        return 2;
    }
    job_t *jobs = calloc(conns, sizeof(job_t));
    pthread_t *threads = calloc(conns, sizeof(pthread_t));
    for (int i = 0; i < conns; i++) {
        jobs[i] = (job_t){argv[1], atoi(argv[2]), atoi(argv[3]), nregs, atof(argv[5]), 0, 0, NULL, 0,
                          MAX_SAMPLES / conns};
        jobs[i].lat_us = malloc(sizeof(float) * jobs[i].cap);
        pthread_create(&threads[i], NULL, run, &jobs[i]);
    }
    long total = 0, errors = 0, nlat = 0;
    for (int i = 0; i < conns; i++) {
        pthread_join(threads[i], NULL);
        if (jobs[i].errors < 0) return 1;
        total += jobs[i].requests;
        errors += jobs[i].errors;
        nlat += jobs[i].nlat;
    }
    float *all = malloc(sizeof(float) * (nlat ? nlat : 1));
    long k = 0;
    for (int i = 0; i < conns; i++) {
        memcpy(all + k, jobs[i].lat_us, sizeof(float) * jobs[i].nlat);
        k += jobs[i].nlat;
    }
    qsort(all, nlat, sizeof(float), cmp);
    double secs = atof(argv[5]);
    printf("requests=%ld errors=%ld rate=%.1f p50_us=%.1f p99_us=%.1f\n", total, errors, total / secs,
           nlat ? all[nlat / 2] : 0.0, nlat ? all[(long)(nlat * 0.99)] : 0.0);
    return 0;
}
