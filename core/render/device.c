/* device.c - the shared Embree device (device.h). */
#include "render/device.h"

#include <pthread.h>
#include <stdatomic.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "util/parallel.h"

struct mr_device {
    RTCDevice rtc;
    unsigned threads;
    atomic_llong embree_bytes;
    pthread_mutex_t error_lock;
    int error_code;      /* RTCError of the last reported error */
    char error_msg[256];
};

static void on_embree_error(void *user, enum RTCError code, const char *str)
{
    mr_device *dev = user;
    pthread_mutex_lock(&dev->error_lock);
    dev->error_code = (int)code;
    snprintf(dev->error_msg, sizeof dev->error_msg, "%s", str ? str : "unknown Embree error");
    pthread_mutex_unlock(&dev->error_lock);
}

static bool on_embree_memory(void *user, ssize_t bytes, bool post)
{
    mr_device *dev = user;
    (void)post;
    atomic_fetch_add(&dev->embree_bytes, (long long)bytes);
    return true; /* never veto: caps are enforced before we reach Embree */
}

int mr_device_new(unsigned threads, mr_device **out, mr_error *err)
{
    *out = NULL;
    mr_device *dev = calloc(1, sizeof *dev);
    if (!dev)
        return mr_error_set(err, MR_ERR_NOMEM, "out of memory creating the device");
    pthread_mutex_init(&dev->error_lock, NULL);
    atomic_init(&dev->embree_bytes, 0);
    dev->threads = threads ? threads : mr_cpu_count();
    char config[64];
    snprintf(config, sizeof config, "threads=%u", dev->threads);
    dev->rtc = rtcNewDevice(config);
    if (!dev->rtc) {
        int code = (int)rtcGetDeviceError(NULL);
        pthread_mutex_destroy(&dev->error_lock);
        free(dev);
        return mr_error_set(err, MR_ERR_EMBREE, "Embree device could not be created (error %d)", code);
    }
    rtcSetDeviceErrorFunction(dev->rtc, on_embree_error, dev);
    rtcSetDeviceMemoryMonitorFunction(dev->rtc, on_embree_memory, dev);
    *out = dev;
    return MR_OK;
}

void mr_device_free(mr_device *dev)
{
    if (!dev)
        return;
    rtcReleaseDevice(dev->rtc);
    pthread_mutex_destroy(&dev->error_lock);
    free(dev);
}

RTCDevice mr_device_embree(const mr_device *dev) { return dev->rtc; }
unsigned mr_device_threads(const mr_device *dev) { return dev->threads; }
int64_t mr_device_embree_bytes(const mr_device *dev)
{
    return atomic_load(&((mr_device *)dev)->embree_bytes);
}

int mr_device_check(mr_device *dev, const char *what, mr_error *err)
{
    int rc = MR_OK;
    pthread_mutex_lock(&dev->error_lock);
    if (dev->error_code != RTC_ERROR_NONE) {
        rc = mr_error_set(err, MR_ERR_EMBREE, "Embree failed in %s: %s", what, dev->error_msg);
        dev->error_code = RTC_ERROR_NONE;
    }
    pthread_mutex_unlock(&dev->error_lock);
    return rc;
}
