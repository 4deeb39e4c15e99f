// Co-simulation harness of dpsa_codec (the row codec's encoder): records on stdin drive the
// model, each row's payload goes to stdout. The records are defined (and documented) in
// fpga/src/codec.rs, which writes them and compares the payloads with dpsa-core's Encoder;
// all integers little-endian.
//
//   tag u32 = 1  stream: width u32, K u32, stall u32 (new stream: command 2 with cmd_k = K,
//                the width register set; stall != 0 inserts pseudo-random gaps in in_valid and
//                drops out_ready pseudo-randomly for the stream's rows)
//   tag u32 = 2  set K: K u32 (command 0)
//   tag u32 = 3  reset: command 1 (forget the reference)
//   tag u32 = 4  row: width x i16 heights, then ceil(width / 8) validity bytes (bit c % 8 of
//                byte c / 8)
//   tag u32 = 5  flush stdout
//   tag u32 = 0  end
//
// Out, per row: len u32 (out_len), clocks u32 (from the first pixel offered to the last word
// accepted), status u32 (bit 0: the word count is not ceil(len / 4), bit 1: a byte past len
// in the last word is not 0), then len payload bytes.
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <vector>

#include "Vdpsa_codec.h"
#include "verilated.h"

namespace {

bool read_all(void* p, size_t len) { return std::fread(p, 1, len, stdin) == len; }

[[noreturn]] void fail(const char* what) {
    std::fprintf(stderr, "codec harness: %s\n", what);
    std::exit(2);
}

uint32_t read_u32() {
    uint32_t v;
    if (!read_all(&v, 4)) fail("truncated record");
    return v;
}

struct Harness {
    std::unique_ptr<VerilatedContext> ctx;
    std::unique_ptr<Vdpsa_codec> m;
    std::vector<uint8_t> out;
    uint32_t width = 1;
    bool stall = false;
    uint32_t lcg = 12345;

    Harness() : ctx(new VerilatedContext), m(new Vdpsa_codec{ctx.get()}) {
        m->clk = 0;
        m->rst = 1;
        m->cmd_valid = 0;
        m->in_valid = 0;
        m->out_ready = 1;
        m->width = 1;
        m->eval();
        for (int i = 0; i < 2; i++) edge();
        m->rst = 0;
        m->eval();
    }

    uint32_t rnd() {
        lcg = lcg * 1664525u + 1013904223u;
        return lcg >> 16;
    }

    // Inputs are set with clk low; the caller samples the handshakes before calling edge().
    void edge() {
        m->clk = 1;
        m->eval();
        m->clk = 0;
        m->eval();
    }

    void command(uint32_t op, uint32_t k) {
        m->in_valid = 0;
        m->cmd_valid = 1;
        m->cmd_op = op;
        m->cmd_k = k;
        m->eval();
        for (int i = 0; !m->cmd_ready; i++) {
            if (i > 100) fail("command not accepted");
            edge();
        }
        edge();
        m->cmd_valid = 0;
        m->eval();
    }

    void row() {
        std::vector<int16_t> h(width);
        std::vector<uint8_t> v((width + 7) / 8);
        if (!read_all(h.data(), 2 * width) || !read_all(v.data(), v.size()))
            fail("truncated row");
        std::vector<uint8_t> bytes;
        uint32_t idx = 0, clocks = 0, len = 0;
        bool done = false;
        const uint64_t limit = 8ull * width + 10000;
        while (!done) {
            bool offer = idx < width && (!stall || rnd() % 4 != 0);
            m->in_valid = offer;
            if (offer) {
                m->in_h = (uint16_t)h[idx];
                m->in_v = (v[idx / 8] >> (idx % 8)) & 1;
            }
            m->out_ready = !stall || rnd() % 3 != 0;
            m->eval();
            bool in_fire = offer && m->in_ready;
            if (m->out_valid && m->out_ready) {
                uint32_t w = m->out_data;
                for (int b = 0; b < 4; b++) bytes.push_back((uint8_t)(w >> (8 * b)));
                if (m->out_last) {
                    len = m->out_len;
                    done = true;
                }
            }
            edge();
            clocks++;
            if (in_fire) idx++;
            if (clocks > limit) fail("the row did not finish");
        }
        m->in_valid = 0;
        m->out_ready = 1;
        m->eval();
        uint32_t status = 0;
        if (bytes.size() != 4 * ((len + 3) / 4)) status |= 1;
        for (size_t i = len; i < bytes.size(); i++)
            if (bytes[i] != 0) status |= 2;
        bytes.resize(len, 0);
        uint32_t hdr[3] = {len, clocks, status};
        out.insert(out.end(), (uint8_t*)hdr, (uint8_t*)hdr + 12);
        out.insert(out.end(), bytes.begin(), bytes.end());
        if (out.size() >= (1 << 20)) flush();
    }

    void flush() {
        if (!out.empty() && std::fwrite(out.data(), 1, out.size(), stdout) != out.size())
            fail("stdout closed");
        out.clear();
        std::fflush(stdout);
    }
};

}  // namespace

int main(int argc, char** argv) {
    Verilated::commandArgs(argc, argv);
    Harness hs;
    for (;;) {
        uint32_t tag = read_u32();
        if (tag == 0) break;
        switch (tag) {
            case 1: {
                uint32_t w = read_u32(), k = read_u32(), st = read_u32();
                if (w < 1 || w > 8192) fail("width out of range");
                hs.width = w;
                hs.stall = st != 0;
                hs.m->width = w;
                hs.command(2, k);
                break;
            }
            case 2: hs.command(0, read_u32()); break;
            case 3: hs.command(1, 0); break;
            case 4: hs.row(); break;
            case 5: hs.flush(); break;
            default: fail("unknown record tag");
        }
    }
    hs.flush();
    hs.m->final();
    return 0;
}
