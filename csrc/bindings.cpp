// The Python module tiger._C. Importing it runs the static TORCH_LIBRARY
// registrations of every op family compiled into the library.
#include <pybind11/pybind11.h>

PYBIND11_MODULE(_C, m) {
  m.doc() = "TIGER compiled core: ops are registered under torch.ops.tiger";
  m.def("cuda_enabled", []() {
#ifdef TIGER_WITH_CUDA
    return true;
#else
    return false;
#endif
  });
}
