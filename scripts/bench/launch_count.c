/* Counts CUDA kernel launches per process, for "kernels per step" (issue 30). Preloaded
 * (LD_PRELOAD) into promptdt or python: every call of the runtime's cudaLaunchKernel (ATen's own
 * kernels) and of the driver's cuLaunchKernel made through the dynamic linker is counted and
 * passed on. Launches that a library makes through a statically linked runtime (cuBLAS's GEMMs)
 * are not seen. At exit the counts go to $LAUNCH_COUNT_DIR/launches.<pid> with the command line.
 * libtorch refers to the runtime's symbols with their version (`cudaLaunchKernel@libcudart.so.13`),
 * so the shim defines that version too (launch_count.map).
 * Build: gcc -O2 -shared -fPIC -Wl,--version-script=launch_count.map -o launch_count.so
 *        launch_count.c -ldl */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <stdio.h>
#include <stdlib.h>
#include <unistd.h>

typedef struct { unsigned x, y, z; } dim3_t;
typedef int (*rt_launch_t)(const void *, dim3_t, dim3_t, void **, size_t, void *);
typedef int (*drv_launch_t)(void *, unsigned, unsigned, unsigned, unsigned, unsigned, unsigned,
                            unsigned, void *, void **, void **);

static unsigned long long n_rt, n_drv;

int cudaLaunchKernel(const void *f, dim3_t g, dim3_t b, void **args, size_t shm, void *s) {
    static rt_launch_t real;
    if (!real) real = (rt_launch_t)dlvsym(RTLD_NEXT, "cudaLaunchKernel", "libcudart.so.13");
    if (!real) real = (rt_launch_t)dlsym(RTLD_NEXT, "cudaLaunchKernel");
    __atomic_add_fetch(&n_rt, 1, __ATOMIC_RELAXED);
    return real(f, g, b, args, shm, s);
}

int cuLaunchKernel(void *f, unsigned gx, unsigned gy, unsigned gz, unsigned bx, unsigned by,
                   unsigned bz, unsigned shm, void *s, void **p, void **e) {
    static drv_launch_t real;
    if (!real) real = (drv_launch_t)dlsym(RTLD_NEXT, "cuLaunchKernel");
    __atomic_add_fetch(&n_drv, 1, __ATOMIC_RELAXED);
    return real(f, gx, gy, gz, bx, by, bz, shm, s, p, e);
}

__attribute__((destructor)) static void report(void) {
    const char *dir = getenv("LAUNCH_COUNT_DIR");
    if (!dir) return;
    char path[4096], cmd[512] = {0};
    snprintf(path, sizeof path, "%s/launches.%d", dir, (int)getpid());
    FILE *c = fopen("/proc/self/cmdline", "r");
    if (c) {
        size_t k = fread(cmd, 1, sizeof cmd - 1, c);
        for (size_t i = 0; i < k; i++) if (!cmd[i]) cmd[i] = ' ';
        fclose(c);
    }
    FILE *o = fopen(path, "w");
    if (!o) return;
    fprintf(o, "runtime %llu driver %llu cmd %s\n", n_rt, n_drv, cmd);
    fclose(o);
}
