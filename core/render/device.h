/*
 * device.h - the process-wide Embree device.
 *
 * One device is shared by every job of a process (Embree devices are heavy:
 * each owns a task scheduler). It carries the worker thread count used for
 * tracing and skinning, a memory monitor that counts the bytes Embree itself
 * allocates (its acceleration structures: microray hands Embree its vertex
 * and index arrays as shared buffers, so they are not counted there), and the
 * last Embree error message.
 */
#ifndef MR_DEVICE_H
#define MR_DEVICE_H

#include <embree3/rtcore.h>

#include "microray.h"

typedef struct mr_device mr_device;

/* threads == 0: all online cores. */
int mr_device_new(unsigned threads, mr_device **out, mr_error *err);
void mr_device_free(mr_device *dev);

RTCDevice mr_device_embree(const mr_device *dev);
unsigned mr_device_threads(const mr_device *dev);
/* Bytes currently allocated by Embree on this device (all scenes). */
int64_t mr_device_embree_bytes(const mr_device *dev);
/* If Embree reported an error since the last call, copy it into err and
 * return MR_ERR_EMBREE; else MR_OK. `what` names the operation. */
int mr_device_check(mr_device *dev, const char *what, mr_error *err);

#endif
