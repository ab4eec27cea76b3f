/* A stand-in libEGL.so.1 for machines without a display whose EGL default display does not work for Blender (bpy as a
 * module makes its GPU context on EGL_DEFAULT_DISPLAY; docs/design-additions.md §49).
 *
 * eglGetDisplay(EGL_DEFAULT_DISPLAY) answers with the display of the first EGL device (EGL_EXT_platform_device);
 * every other EGL function is the real library's. The real glvnd libEGL sits beside this one as libEGL_real.so.1, a
 * dependency of this library, so a dlsym() on this library's handle (libepoxy's way) finds them.
 * headless/gpu_payload.py builds it; SGLF_EGL_DEVICE_LOG=1 prints the display it chose. */
#include <EGL/egl.h>
#include <EGL/eglext.h>
#include <dlfcn.h>
#include <stdio.h>
#include <stdlib.h>

EGLDisplay eglGetDisplay(EGLNativeDisplayType display_id)
{
  if (display_id == EGL_DEFAULT_DISPLAY) {
    PFNEGLQUERYDEVICESEXTPROC query_devices = (PFNEGLQUERYDEVICESEXTPROC)eglGetProcAddress("eglQueryDevicesEXT");
    EGLDeviceEXT devices[8];
    EGLint count = 0;
    if (query_devices && query_devices(8, devices, &count) && count > 0) {
      EGLDisplay display = eglGetPlatformDisplay(EGL_PLATFORM_DEVICE_EXT, devices[0], NULL);
      if (getenv("SGLF_EGL_DEVICE_LOG")) {
        fprintf(stderr, "egl_device_display: the default display is device 0 of %d (%s)\n", count,
                display == EGL_NO_DISPLAY ? "no display" : "a display");
      }
      if (display != EGL_NO_DISPLAY) {
        return display;
      }
    }
  }
  void *real = dlopen("libEGL_real.so.1", RTLD_NOW | RTLD_NOLOAD);
  EGLDisplay (*real_get_display)(EGLNativeDisplayType) = real ? dlsym(real, "eglGetDisplay") : NULL;
  return real_get_display ? real_get_display(display_id) : EGL_NO_DISPLAY;
}
