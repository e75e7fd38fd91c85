// The kernels' avx2 build (setup.py): the bindings and kernels in a file of its own, so that the
// builds compiled side by side write object files of their own (one shared source gave them
// one object path, and a build could link another's object: _kernels_base defining
// PyInit__kernels_avx2).
#include "_bindings.cpp"
