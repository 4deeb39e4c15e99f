// Co-simulation harness: the Verilator model of dpsa_pixel, driven by records on stdin, its
// outputs on stdout. The record format is defined (and documented) in fpga/src/cosim.rs, which
// writes the records and compares the outputs with dpsa-core; all integers little-endian.
//
//   tag u32 = 1  window: n u32, q2[8] i32, q3[8] i32, sat u32, fast u32, thr2 u64, half u32,
//                sh u32, rho u32 (the pipeline is drained before the registers change, as the
//                MCU writes them between rows)
//   tag u32 = 2  pixels: count u32, then count x (x[8] u16, ref_phase u32, k u32); the batch's
//                outputs are all written before the next record is read
//   tag u32 = 0  end: drain and exit
//
// Out, one record of 16 bytes a pixel in input order: v2 i32, v3 i32, phi u32, h i16, flags u16
// (bit 0 valid, bit 1 saturated, bit 2 low modulation).
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <vector>

#include "Vdpsa_pixel.h"
#include "verilated.h"

namespace {

bool read_all(void* p, size_t len) { return std::fread(p, 1, len, stdin) == len; }

[[noreturn]] void fail(const char* what) {
    std::fprintf(stderr, "harness: %s\n", what);
    std::exit(2);
}

struct Harness {
    std::unique_ptr<VerilatedContext> ctx;
    std::unique_ptr<Vdpsa_pixel> m;
    std::vector<uint8_t> out;
    uint64_t in_flight = 0;

    Harness() : ctx(new VerilatedContext), m(new Vdpsa_pixel{ctx.get()}) {
        m->clk = 0;
        m->in_valid = 0;
        m->eval();
    }

    void tick() {
        m->clk = 1;
        m->eval();
        // Outputs of this edge.
        if (m->out_valid) {
            uint8_t rec[16];
            uint32_t v2 = m->v2, v3 = m->v3, phi = m->phi;
            uint16_t h = m->h;
            uint16_t fl = (m->px_valid ? 1 : 0) | (m->px_saturated ? 2 : 0) |
                          (m->px_low_modulation ? 4 : 0);
            std::memcpy(rec, &v2, 4);
            std::memcpy(rec + 4, &v3, 4);
            std::memcpy(rec + 8, &phi, 4);
            std::memcpy(rec + 12, &h, 2);
            std::memcpy(rec + 14, &fl, 2);
            out.insert(out.end(), rec, rec + 16);
            if (in_flight == 0) fail("an output without an input");
            in_flight--;
        }
        m->clk = 0;
        m->eval();
        if (out.size() >= (1 << 20)) flush();
    }

    void drain() {
        m->in_valid = 0;
        // Bounded: the pipeline's latency is fixed; a model that never answers is an error.
        for (int i = 0; in_flight > 0; i++) {
            if (i > 1000) fail("the pipeline did not drain");
            tick();
        }
    }

    void flush() {
        if (!out.empty() && std::fwrite(out.data(), 1, out.size(), stdout) != out.size())
            fail("stdout closed");
        // A pipe is block-buffered: the other end may be waiting for exactly these bytes.
        if (std::fflush(stdout) != 0) fail("stdout closed");
        out.clear();
    }

    void set_wide(uint32_t* w, const int32_t* v) {
        // Eight 16-bit lanes, lane j at bits 16j..16j+15.
        for (int i = 0; i < 4; i++)
            w[i] = (uint32_t)(uint16_t)v[2 * i] | ((uint32_t)(uint16_t)v[2 * i + 1] << 16);
    }

    void window() {
        uint32_t n;
        int32_t q2[8], q3[8];
        uint32_t sat, fast, half, sh, rho;
        uint64_t thr2;
        if (!read_all(&n, 4) || !read_all(q2, 32) || !read_all(q3, 32) || !read_all(&sat, 4) ||
            !read_all(&fast, 4) || !read_all(&thr2, 8) || !read_all(&half, 4) ||
            !read_all(&sh, 4) || !read_all(&rho, 4))
            fail("truncated window record");
        drain();
        m->n = n;
        set_wide(m->q2.data(), q2);
        set_wide(m->q3.data(), q3);
        m->sat = sat;
        m->fast = fast;
        m->thr2 = thr2;
        m->half = half;
        m->sh = sh;
        m->rho = rho;
    }

    void pixels() {
        uint32_t count;
        if (!read_all(&count, 4)) fail("truncated pixel count");
        uint8_t rec[24];
        for (uint32_t p = 0; p < count; p++) {
            if (!read_all(rec, 24)) fail("truncated pixel record");
            for (int i = 0; i < 4; i++) {
                uint32_t w;
                std::memcpy(&w, rec + 4 * i, 4);
                m->x[i] = w;
            }
            uint32_t ref, k;
            std::memcpy(&ref, rec + 16, 4);
            std::memcpy(&k, rec + 20, 4);
            m->ref_phase = ref;
            m->k = k;
            m->in_valid = 1;
            in_flight++;
            tick();
        }
        // Every batch answered in full before the next is read: the other end may wait for
        // these outputs before it writes more.
        drain();
        flush();
    }
};

}  // namespace

int main(int argc, char** argv) {
    Verilated::commandArgs(argc, argv);
    Harness hs;
    for (;;) {
        uint32_t tag;
        if (!read_all(&tag, 4)) fail("input ended without an end record");
        if (tag == 0) break;
        if (tag == 1)
            hs.window();
        else if (tag == 2)
            hs.pixels();
        else
            fail("unknown record tag");
    }
    hs.drain();
    hs.flush();
    hs.m->final();
    return 0;
}
