# Third-party dependencies, all from Debian packages.
#
# OpenCV: Debian ships OpenCVConfig.cmake only in libopencv-dev, which pulls every
# module (highgui/Qt, viz/VTK, dnn, ...). We need core, imgproc, features2d and (for
# replay/tools) imgcodecs, so we locate those modules' headers and libraries directly and
# expose them as imported targets mer::opencv_<module>.

find_package(Threads REQUIRED)
find_package(Eigen3 3.3 QUIET NO_MODULE)
# Ceres (libceres-dev): bundle adjustment of the covisibility window.
find_package(Ceres 2.1 QUIET)

find_path(MER_OPENCV_INCLUDE_DIR opencv2/core.hpp PATH_SUFFIXES opencv4)
set(MER_OPENCV_MODULES core imgproc features2d imgcodecs)
set(MER_OPENCV_FOUND TRUE)
foreach(mod IN LISTS MER_OPENCV_MODULES)
  find_library(MER_OPENCV_${mod}_LIBRARY NAMES opencv_${mod})
  if(MER_OPENCV_${mod}_LIBRARY AND MER_OPENCV_INCLUDE_DIR)
    if(NOT TARGET mer::opencv_${mod})
      add_library(mer::opencv_${mod} UNKNOWN IMPORTED)
      set_target_properties(mer::opencv_${mod} PROPERTIES
        IMPORTED_LOCATION "${MER_OPENCV_${mod}_LIBRARY}"
        INTERFACE_INCLUDE_DIRECTORIES "${MER_OPENCV_INCLUDE_DIR}")
    endif()
  else()
    set(MER_OPENCV_FOUND FALSE)
  endif()
endforeach()

if(TARGET Eigen3::Eigen AND MER_OPENCV_FOUND AND TARGET Ceres::ceres)
  set(MER_HAVE_CORE_DEPS TRUE)
  # imgproc/features2d depend on core at link time.
  set_property(TARGET mer::opencv_imgproc APPEND PROPERTY INTERFACE_LINK_LIBRARIES mer::opencv_core)
  set_property(TARGET mer::opencv_features2d APPEND PROPERTY INTERFACE_LINK_LIBRARIES mer::opencv_imgproc)
  set_property(TARGET mer::opencv_imgcodecs APPEND PROPERTY INTERFACE_LINK_LIBRARIES mer::opencv_imgproc)
else()
  set(MER_HAVE_CORE_DEPS FALSE)
endif()
message(STATUS "mer-slam: Eigen3 ${Eigen3_VERSION}, OpenCV modules found: ${MER_OPENCV_FOUND}, "
               "Ceres ${Ceres_VERSION}")
