/*
 * device.h - the Embree side of the process-wide device (mr_device, whose
 * new/free/threads are public: microray.h): the RTCDevice the kinds and the
 * renderer build on, Embree's allocated bytes and its last error.
 */
#ifndef MR_DEVICE_H
#define MR_DEVICE_H

#include <embree3/rtcore.h>

#include "microray.h"

RTCDevice mr_device_embree(const mr_device *dev);
/* Bytes currently allocated by Embree on this device (all scenes). */
int64_t mr_device_embree_bytes(const mr_device *dev);
/* If Embree reported an error since the last call, copy it into err and
 * return MR_ERR_EMBREE; else MR_OK. `what` names the operation. */
int mr_device_check(mr_device *dev, const char *what, mr_error *err);

#endif
