# Included by DC's interface packages after rosidl_generate_interfaces(), and needed only with the
# ROS 2 wheels from PyPI (a ROS installation from a distribution builds without it, which is why the
# packages include it OPTIONAL): their exported `<pkg>__rosidl_generator_py` targets have include
# directories of the machine they were built on (/opt/python/cp311-cp311/include/python3.11, numpy's
# include dir there), and CMake's generate step rejects non-existent include paths of imported
# targets. Point them at this machine's Python and NumPy headers (the package found Python3 with
# NumPy before rosidl_generate_interfaces()). Properties are read at generate time, so the targets
# rosidl_generate_interfaces() imported are covered too.
get_property(_dc_imported_targets DIRECTORY PROPERTY IMPORTED_TARGETS)
foreach(_dc_target IN LISTS _dc_imported_targets)
  if(_dc_target MATCHES "__rosidl_generator_py$")
    set_target_properties(${_dc_target} PROPERTIES
      INTERFACE_INCLUDE_DIRECTORIES "${Python3_INCLUDE_DIRS};${Python3_NumPy_INCLUDE_DIRS}")
  endif()
endforeach()
