// The kernels' avx2 build: a source of its own per variant (why: setup.py, extensions()).
#include "_bindings.cpp"
