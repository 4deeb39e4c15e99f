// dpsa_codec: the lossless row codec's encoder in the fabric, byte for byte the payload of
// dpsa_core::packets::codec::Encoder::encode (core/src/packets/codec.rs specifies the
// format: header, intra / predicted rows, validity section, predictor, contexts, adaptive
// Rice code, raw fallback).
//
// ## Interface
//
// Control (accepted only between rows: cmd_ready is high while the codec is idle):
//   cmd_op 0  set the intra period K = cmd_k (Encoder::set_intra_period: the budget of
//             predicted rows is cut to K - 1 at once)
//   cmd_op 1  forget the reference (Encoder::reset): the next row is intra
//   cmd_op 2  new stream (Encoder::new): no reference, sequence number 0, budget 0, K = cmd_k
// `width` (1 ..= 8192) is sampled when a row's first pixel is offered; a stream keeps one
// width (changing it needs command 1 or 2 first, as the core needs a new Encoder).
//
// Pixels: in_valid / in_ready, in_h (the height, i16) and in_v (1 = valid), left to right,
// `width` of them per row. in_ready is high for the whole input pass, so a row goes in at one
// pixel a clock (gaps in in_valid are allowed); it is low while the codec starts a row, drains
// its pipeline and writes the payload out.
//
// Payload: out_valid / out_ready, out_data: 32-bit words of payload bytes, byte 0 of the
// payload in out_data[7:0] (little-endian: a DMA writes the bytes in order to memory).
// out_last marks the row's last word; out_len (bytes, 2 + ... <= 17410) is valid with it. The
// last word's bytes past out_len are 0. Word count = ceil(out_len / 4).
//
// ## Clocks per row (no back-pressure, no input gaps)
//
//   1 (start) + 2 (prefetch) + W (input pass) + 12 (drain) + 2 (decide)
//   + output pass: 1 header item + ceil(V / 32) validity words + the body items + 5 (its
//     pipeline and the last handshake)
//     coded row: body = ceil(P / 32) words of pixel codes (P = bits of the Rice codes,
//                V = bits of the validity section)
//     raw row:   body = W items of 16 bits (the heights), validity = ceil(W / 32) words
// i.e. (measured by the co-simulation) W + ceil(payload bytes / 4) + 23 clocks for a coded
// row (W = 2048 at ~5.4 bits/pixel: about 2048 + 346 + 23), about 2 W + W / 32 + 23 for a
// raw row.
//
// ## Stages
//
// Input pass (one pixel a clock):
//   stage 0  the reference window U[c-1], U[c], U[c+1] (registers fed by the reference RAM,
//            read three pixels ahead; a raw or intra previous row is stored unfilled and filled
//            here on the fly: U[c] = its last valid height to the left, 0 before any), the
//            filled height R[c] and R[c-1], R[c-2]; R[c] and valid(c) written back to the
//            reference RAM at c (the read pointer is three ahead, so no hazard); m(c) into the
//            run tracker (each finished run goes, as Elias gamma, to the validity packer);
//            valid(c) into the plain mask words.
//   stage 1  the predictor's terms: the gradients' absolute differences, the averages, MED's
//            comparisons; (1b) the gradient sums and MED; (1c) the prediction (predicted:
//            4-neighbour average or MED by the gradient; intra: the 2-neighbour average or the
//            left neighbour), the context t, the residual mod 2^16 and its zigzag z.
//   stage 2  the context's accumulator A gives k = bitlen(A >> 6); A -= A >> 5, A += z (the
//            only loop: one clock); then (2b) the Rice code (or the escape: 16 zeros and z) as
//            up to 32 bits and a length.
//   stage 3  the pixel packer (align, merge): 32-bit words into the pixel buffer.
// Drain and decide: both packers flushed; the validity section is plain when the runs take
// more than W bits; coded length = 2 + ceil((V + P) / 8); raw when that exceeds the raw
// payload; header, sequence number, budget and reference mode updated as the Encoder does.
// Output pass: the header, the validity words (plain mask or runs; for a raw row the plain
// mask with each byte's bits reversed, i.e. the raw validity bytes) and the pixel-code words
// (raw row: the heights read back from the reference RAM, 0 where invalid, little-endian) go
// through a merging shifter (64-bit accumulator, up to 32 bits in, a word out per clock):
// item -> RAM read -> read register -> select -> merge -> word register.
// One stall signal (out_valid && !out_ready) holds the whole output pipeline, RAM read
// registers included.
//
// ## Synthesis (fpga/synth/run.sh --design codec, LFE5U-85F, yosys + nextpnr-ecp5, seed 1)
//
//   fmax 89 MHz; 5069 LUT4, 1809 FF, 19 DP16KD, 0 DSP. The critical path is the pixel-code
//   buffer's read (9 cascaded blocks and their output mux) into its read register.
//
// ## Block RAM (ECP5 DP16KD, 18 kbit each)
//
//   reference   8192 x 17  (R and the validity bit)            8 blocks (1024 x 18)
//   pixel codes 4608 x 32  (a coded row never needs more than 8 (ceil(W/8) + 2 W) bits,
//                           4352 words at W = 8192; words past the buffer are counted only)
//                                                              9 blocks (512 x 36)
//   runs         256 x 32  (used only when the runs take <= W bits)   1 block
//   plain mask   256 x 32                                             1 block
// The reference rule: R of a coded predicted row is stored filled (U where invalid); an
// intra or raw row is stored as its heights and validity and filled when read (`fill_mode`),
// which gives a predicted row that fell back to raw the intra fill the Encoder writes.
`default_nettype none

module dpsa_codec (
    input  wire        clk,
    input  wire        rst,
    // control
    input  wire        cmd_valid,
    output wire        cmd_ready,
    input  wire [1:0]  cmd_op,
    input  wire [15:0] cmd_k,
    input  wire [13:0] width,
    // pixels
    input  wire        in_valid,
    output wire        in_ready,
    input  wire [15:0] in_h,
    input  wire        in_v,
    // payload
    output reg         out_valid,
    input  wire        out_ready,
    output reg  [31:0] out_data,
    output reg         out_last,
    output reg  [15:0] out_len
);
    localparam [2:0] S_IDLE = 3'd0, S_PREP = 3'd1, S_RUN = 3'd2, S_DRAIN = 3'd3,
                     S_DECIDE = 3'd4, S_OUT = 3'd5, S_DECIDE0 = 3'd6, S_PREP1 = 3'd7;
    localparam integer PIX_WORDS = 4608;

    reg [2:0] state;

    // ---- stream state (the Encoder's fields) ----
    reg        present;    // a reference is held
    reg [15:0] kreg;       // intra period K
    reg [15:0] budget;     // predicted rows still allowed
    reg [7:0]  seq;        // next sequence number
    reg        fill_mode;  // the stored reference is unfilled (last row intra or raw)

    // ---- row state ----
    reg [13:0] wreg;       // W
    reg [13:0] wlast;      // W - 1
    reg        pred;       // this row is predicted
    reg [12:0] col;        // input pixel index
    reg [3:0]  dcnt;       // drain counter

    // ---- reference RAM: {valid, R} ----
    reg [16:0] ref_mem [0:8191];
    reg [16:0] ref_q;      // read data
    reg [16:0] ref_q2;     // the input pass's copy, one clock later
    reg        ref_re;
    reg [12:0] ref_ra;

    // ---- output pass ----
    localparam [2:0] O_HDR = 3'd0, O_VAL = 3'd1, O_PIX = 3'd2, O_FLUSH = 3'd3, O_WAIT = 3'd4;
    reg [2:0]  ophase;
    reg [13:0] oidx;
    wire       oadv = (state == S_OUT) && (!out_valid || out_ready);

    assign cmd_ready = (state == S_IDLE);
    assign in_ready  = (state == S_RUN);

    wire adv  = (state == S_RUN) && in_valid;
    wire last = ({1'b0, col} == wlast);

    // =====================================================================================
    // Stage 0: reference window, filled heights, write-back, runs, plain mask
    // =====================================================================================
    reg [15:0] u_m1, u_0;  // U[c-1], U[c]
    reg        rv_0;       // reference validity of pixel c
    reg [15:0] r_m1, r_m2; // R[c-1], R[c-2]

    wire        q_v    = ref_q2[16];
    wire [15:0] q_s    = ref_q2[15:0];
    wire [15:0] u_next = (fill_mode && !q_v) ? u_0 : q_s;   // U[c+1]
    wire [15:0] d0     = last ? u_0 : u_next;               // U[W] = U[W-1]
    wire [15:0] r0     = in_v ? in_h : (pred ? u_0 : r_m1);
    wire        m0     = in_v ^ (pred ? rv_0 : 1'b1);
    // At the prefetch: U[0] (filled: 0 when pixel 0 was invalid in an intra / raw row).
    wire [15:0] u_first = (fill_mode && !q_v) ? 16'd0 : q_s;

    // Reference RAM read port: address 0 while idle, 1 and 2 in the prefetch, c + 3 in the
    // input pass (two registers, ref_q and ref_q2, both advancing with the input: ref_q2 holds
    // U[c+1] when pixel c comes), the output index in the output pass.
    always @(*) begin
        ref_re = 1'b0;
        ref_ra = 13'd0;
        case (state)
            S_IDLE: begin ref_re = 1'b1; ref_ra = 13'd0; end
            S_PREP: begin ref_re = 1'b1; ref_ra = 13'd1; end
            S_PREP1: begin ref_re = 1'b1; ref_ra = 13'd2; end
            S_RUN:  begin ref_re = adv;  ref_ra = col + 13'd3; end
            S_OUT:  begin ref_re = oadv; ref_ra = oidx[12:0]; end
            default: ;
        endcase
    end

    always @(posedge clk) begin
        if (adv) ref_mem[col] <= {in_v, r0};
        if (ref_re) ref_q <= ref_mem[ref_ra];
        if (state == S_PREP || state == S_PREP1 || adv) ref_q2 <= ref_q;
    end

    // Stage 1 inputs.
    reg        s1_valid;
    reg [15:0] s1_x, s1_a, s1_aa, s1_b, s1_u, s1_d;

    // Run tracker: the current run's value, length, and whether it started at pixel 0.
    reg        run_val;
    reg [13:0] run_len;
    reg        run_at0;
    reg        gq_valid;   // a run length to code
    reg [13:0] gq_val;

    // Plain mask words: valid(32 i) at bit 31.
    reg [31:0] pw;
    reg [31:0] plain_mem [0:255];
    wire [31:0] pw_next = (col[4:0] == 5'd0 ? 32'd0 : pw) | ({in_v, 31'd0} >> col[4:0]);

    always @(posedge clk) begin
        s1_valid <= adv && in_v;
        gq_valid <= 1'b0;
        if (state == S_PREP1) begin
            u_m1 <= u_first;
            u_0  <= u_first;
            rv_0 <= q_v;
            r_m1 <= pred ? u_first : 16'd0;
            r_m2 <= 16'd0;
        end
        if (adv) begin
            u_m1 <= u_0;
            u_0  <= u_next;
            rv_0 <= q_v;
            r_m2 <= r_m1;
            r_m1 <= r0;
            s1_x  <= in_h;
            s1_a  <= r_m1;
            s1_aa <= r_m2;
            s1_b  <= u_0;
            s1_u  <= u_m1;
            s1_d  <= d0;
            pw <= pw_next;
            if (col[4:0] == 5'd31 || last) plain_mem[col[12:5]] <= pw_next;
            if (col == 13'd0) begin
                run_val <= m0;
                run_len <= 14'd1;
                run_at0 <= 1'b1;
                if (m0) begin          // the empty first run of 0s: gamma(1)
                    gq_valid <= 1'b1;
                    gq_val   <= 14'd1;
                end
            end else if (m0 == run_val) begin
                run_len <= run_len + 14'd1;
            end else begin
                gq_valid <= 1'b1;
                gq_val   <= run_len + {13'd0, run_at0};
                run_val  <= m0;
                run_len  <= 14'd1;
                run_at0  <= 1'b0;
            end
        end
        if (state == S_DRAIN && dcnt == 4'd0) begin   // the last run
            gq_valid <= 1'b1;
            gq_val   <= run_len + {13'd0, run_at0};
        end
    end

    // Elias gamma of the run: bitlen(v) - 1 zeros then v, i.e. v in 2 bitlen(v) - 1 bits.
    function automatic [3:0] bitlen14(input [13:0] v);
        integer i;
        begin
            bitlen14 = 4'd0;
            for (i = 0; i < 14; i = i + 1)
                if (v[i]) bitlen14 = i[3:0] + 4'd1;
        end
    endfunction
    wire [3:0] g_nb  = bitlen14(gq_val);
    reg        g2_valid;
    reg [13:0] g2_val;
    reg [5:0]  g2_len;
    always @(posedge clk) begin
        g2_valid <= gq_valid;
        g2_val   <= gq_val;
        g2_len   <= {1'b0, g_nb, 1'b0} - 6'd1;
    end

    wire        gpk_we;
    wire [12:0] gpk_waddr;
    wire [31:0] gpk_wdata;
    wire [19:0] vbits;
    reg  [31:0] gam_mem [0:255];
    wire        pk_flush = (state == S_DRAIN) && (dcnt == 4'd8);

    dpsa_codec_pack gpk (
        .clk(clk), .clr(state == S_PREP), .in_valid(g2_valid), .in_bits({18'd0, g2_val}),
        .in_len(g2_len), .flush(pk_flush), .we(gpk_we), .waddr(gpk_waddr), .wdata(gpk_wdata),
        .nbits(vbits)
    );
    always @(posedge clk)
        if (gpk_we && gpk_waddr[12:8] == 5'd0) gam_mem[gpk_waddr[7:0]] <= gpk_wdata;

    // =====================================================================================
    // Stage 1: predictor, context, zigzag residual
    // =====================================================================================
    function automatic [17:0] abs18(input signed [17:0] v);
        abs18 = v[17] ? -v : v;
    endfunction

    wire signed [17:0] ea  = {{2{s1_a[15]}},  s1_a};
    wire signed [17:0] eaa = {{2{s1_aa[15]}}, s1_aa};
    wire signed [17:0] eb  = {{2{s1_b[15]}},  s1_b};
    wire signed [17:0] eu  = {{2{s1_u[15]}},  s1_u};
    wire signed [17:0] ed  = {{2{s1_d[15]}},  s1_d};

    // Stage 1a: the gradients' terms, the averages, MED's comparisons.
    wire signed [17:0] sum4 = ea + eb + eu + ed + 18'sd2;
    wire signed [17:0] avg4 = sum4 >>> 2;
    wire signed [17:0] sum2 = ea + eaa + 18'sd1;
    wire signed [17:0] avg2 = sum2 >>> 1;
    wire signed [17:0] abmu = ea + eb - eu;

    reg        h_valid;
    reg [17:0] h_au, h_ub, h_bd, h_gi;
    reg [15:0] h_avg4, h_avg2, h_abmu, h_a, h_b, h_x;
    reg        h_u_ge_a, h_u_ge_b, h_u_le_a, h_u_le_b, h_a_lt_b;
    always @(posedge clk) begin
        h_valid  <= s1_valid;
        h_au     <= abs18(ea - eu);
        h_ub     <= abs18(eu - eb);
        h_bd     <= abs18(eb - ed);
        h_gi     <= abs18(ea - eaa);
        h_avg4   <= avg4[15:0];
        h_avg2   <= avg2[15:0];
        h_abmu   <= abmu[15:0];
        h_u_ge_a <= eu >= ea;
        h_u_ge_b <= eu >= eb;
        h_u_le_a <= eu <= ea;
        h_u_le_b <= eu <= eb;
        h_a_lt_b <= ea < eb;
        h_a      <= s1_a;
        h_b      <= s1_b;
        h_x      <= s1_x;
    end

    // Stage 1b: g = |a-u| + |u-b| + |b-d|; MED(a, b, u) (LOCO-I: min(a,b) if u >= max(a,b),
    // max(a,b) if u <= min(a,b), else a + b - u).
    wire [19:0] gp = {2'd0, h_au} + {2'd0, h_ub} + {2'd0, h_bd};
    wire [15:0] mn = h_a_lt_b ? h_a : h_b;
    wire [15:0] mx = h_a_lt_b ? h_b : h_a;
    wire [15:0] med = (h_u_ge_a && h_u_ge_b) ? mn : (h_u_le_a && h_u_le_b) ? mx : h_abmu;

    reg        t_valid;
    reg [19:0] t_gp;
    reg [17:0] t_gi;
    reg [15:0] t_avg4, t_med, t_avg2, t_a, t_x;
    always @(posedge clk) begin
        t_valid <= h_valid;
        t_gp    <= gp;
        t_gi    <= h_gi;
        t_avg4  <= h_avg4;
        t_med   <= med;
        t_avg2  <= h_avg2;
        t_a     <= h_a;
        t_x     <= h_x;
    end

    // Stage 1c: predicted row: the average if g < 128 (context 0 / 1 by g < 48), else MED
    // (context 2); intra row: the average if |a - aa| < 48 (context 0 / 1 by 16), else a.
    wire        p_flat = t_gp < 20'd128;
    wire [15:0] p_pred = p_flat ? t_avg4 : t_med;
    wire [1:0]  p_t    = p_flat ? {1'b0, t_gp >= 20'd48} : 2'd2;
    wire        i_flat = t_gi < 18'd48;
    wire [15:0] i_pred = i_flat ? t_avg2 : t_a;
    wire [1:0]  i_t    = i_flat ? {1'b0, t_gi >= 18'd16} : 2'd2;

    wire [15:0] e1 = t_x - (pred ? p_pred : i_pred);
    wire [15:0] z1 = {e1[14:0], 1'b0} ^ {16{e1[15]}};

    reg        s2_valid;
    reg [15:0] s2_z;
    reg [1:0]  s2_t;
    always @(posedge clk) begin
        s2_valid <= t_valid;
        s2_z <= z1;
        s2_t <= pred ? p_t : i_t;
    end

    // =====================================================================================
    // Stage 2: adaptive Rice parameter and code
    // =====================================================================================
    localparam [20:0] A_INIT = 21'd448;
    reg [20:0] acc0, acc1, acc2;
    wire [20:0] asel = (s2_t == 2'd0) ? acc0 : (s2_t == 2'd1) ? acc1 : acc2;
    function automatic [3:0] bitlen15(input [14:0] v);
        integer i;
        begin
            bitlen15 = 4'd0;
            for (i = 0; i < 15; i = i + 1)
                if (v[i]) bitlen15 = i[3:0] + 4'd1;
        end
    endfunction
    wire [3:0]  rk    = bitlen15(asel[20:6]);
    wire [20:0] anew  = asel - {5'd0, asel[20:5]} + {5'd0, s2_z};

    // Stage 2b: the Rice code of z with parameter k, or the escape.
    reg        c_valid;
    reg [15:0] c_z;
    reg [3:0]  c_k;
    wire [15:0] rn    = c_z >> c_k;
    wire        resc  = rn[15:4] != 12'd0;
    wire [31:0] rone  = 32'd1 << c_k;
    wire [31:0] rbits = resc ? {16'd0, c_z} : (rone | ({16'd0, c_z} & (rone - 32'd1)));
    wire [5:0]  rlen  = resc ? 6'd32 : ({2'd0, rn[3:0]} + {2'd0, c_k} + 6'd1);

    reg        s3_valid;
    reg [31:0] s3_bits;
    reg [5:0]  s3_len;
    always @(posedge clk) begin
        c_valid  <= s2_valid;
        c_z      <= s2_z;
        c_k      <= rk;
        s3_valid <= c_valid;
        s3_bits  <= rbits;
        s3_len   <= rlen;
        if (state == S_PREP) begin
            acc0 <= A_INIT;
            acc1 <= A_INIT;
            acc2 <= A_INIT;
        end else if (s2_valid) begin
            case (s2_t)
                2'd0: acc0 <= anew;
                2'd1: acc1 <= anew;
                default: acc2 <= anew;
            endcase
        end
    end

    // =====================================================================================
    // Stage 3: pixel packer into the pixel-code buffer
    // =====================================================================================
    wire        ppk_we;
    wire [12:0] ppk_waddr;
    wire [31:0] ppk_wdata;
    wire [19:0] pbits;
    reg  [31:0] pix_mem [0:PIX_WORDS-1];
    dpsa_codec_pack ppk (
        .clk(clk), .clr(state == S_PREP), .in_valid(s3_valid), .in_bits(s3_bits),
        .in_len(s3_len), .flush(pk_flush), .we(ppk_we), .waddr(ppk_waddr), .wdata(ppk_wdata),
        .nbits(pbits)
    );
    always @(posedge clk)
        if (ppk_we && {19'd0, ppk_waddr} < PIX_WORDS) pix_mem[ppk_waddr] <= ppk_wdata;

    // =====================================================================================
    // Decide: plain or runs, coded or raw, the header; the stream state
    // =====================================================================================
    // Decide, first clock: the section lengths.
    wire [20:0] w21     = {7'd0, wreg};
    wire        plain   = {1'b0, vbits} > w21;
    wire [20:0] vsec    = plain ? w21 : {1'b0, vbits};
    wire [20:0] cbits   = vsec + {1'b0, pbits} + 21'd7;
    wire [17:0] rawlen  = {7'd0, wreg[13:3]} + {17'd0, wreg[2:0] != 3'd0} + {3'd0, wreg, 1'b0};
    reg         d_plain;
    reg  [17:0] d_cbytes, d_rawlen;
    always @(posedge clk)
        if (state == S_DECIDE0) begin
            d_plain  <= plain;
            d_cbytes <= cbits[20:3];
            d_rawlen <= rawlen;
        end
    // Second clock: raw or coded, the payload length.
    wire        raw     = d_cbytes > d_rawlen;
    wire [17:0] plen    = 18'd2 + (raw ? d_rawlen : d_cbytes);
    wire [13:0] wm1     = wreg - 14'd1;
    wire [19:0] vm1     = vbits - 20'd1;
    wire [19:0] pm1     = pbits - 20'd1;

    // Bits the arithmetic above carries but the design never needs.
    /* verilator lint_off UNUSEDSIGNAL */
    wire unused_bits = &{1'b0, avg4[17:16], abmu[17:16], avg2[17:16], cbits[2:0], plen[17:16],
                         vm1[19:14], pm1[19], wm1[4:0]};
    /* verilator lint_on UNUSEDSIGNAL */

    reg        o_raw;
    reg [7:0]  o_hdr_flags, o_hdr_seq;
    reg [13:0] o_nvm1;     // validity words - 1
    reg [5:0]  o_vlast;    // bits of the last validity word
    reg [13:0] o_npm1;     // body items - 1
    reg        o_np0;      // no body items
    reg [5:0]  o_plast;    // bits of the last pixel-code word
    reg        o_vsrc_plain;
    reg [13:0] o_nwm1;     // payload words - 1
    reg [13:0] owc;        // words emitted

    // =====================================================================================
    // Output pass: items -> RAM reads -> merging shifter -> word register
    // =====================================================================================
    localparam [2:0] B_HDR = 3'd0, B_PLAIN = 3'd1, B_GAM = 3'd2, B_PIX = 3'd3, B_REF = 3'd4;
    reg        it_valid, it_flush;
    reg [2:0]  it_src;
    reg [5:0]  it_len;
    reg [2:0]  ophase_n;
    reg [13:0] oidx_n;
    always @(*) begin
        it_valid = 1'b0;
        it_flush = 1'b0;
        it_src   = B_HDR;
        it_len   = 6'd0;
        ophase_n = ophase;
        oidx_n   = oidx;
        case (ophase)
            O_HDR: begin
                it_valid = 1'b1;
                it_len   = 6'd16;
                ophase_n = O_VAL;
                oidx_n   = 14'd0;
            end
            O_VAL: begin
                it_valid = 1'b1;
                it_src   = o_vsrc_plain ? B_PLAIN : B_GAM;
                it_len   = (oidx == o_nvm1) ? o_vlast : 6'd32;
                if (oidx == o_nvm1) begin
                    ophase_n = o_np0 ? O_FLUSH : O_PIX;
                    oidx_n   = 14'd0;
                end else begin
                    oidx_n = oidx + 14'd1;
                end
            end
            O_PIX: begin
                it_valid = 1'b1;
                it_src   = o_raw ? B_REF : B_PIX;
                it_len   = o_raw ? 6'd16 : (oidx == o_npm1) ? o_plast : 6'd32;
                if (oidx == o_npm1) ophase_n = O_FLUSH;
                oidx_n = oidx + 14'd1;
            end
            O_FLUSH: begin
                it_valid = 1'b1;
                it_flush = 1'b1;
                ophase_n = O_WAIT;
            end
            default: ;
        endcase
    end

    reg [31:0] plain_q, gam_q, pix_q;
    always @(posedge clk)
        if (oadv) begin
            plain_q <= plain_mem[oidx[7:0]];
            gam_q   <= gam_mem[oidx[7:0]];
            pix_q   <= pix_mem[oidx[12:0]];
        end

    reg        b_valid, b_flush;
    reg [2:0]  b_src;
    reg [5:0]  b_len;
    // The read data registered once more (the RAMs are cascades of blocks with an output mux).
    reg        b2_valid, b2_flush;
    reg [2:0]  b2_src;
    reg [5:0]  b2_len;
    reg [31:0] plain_q2, gam_q2, pix_q2;
    reg [16:0] refo_q2;
    always @(posedge clk)
        if (oadv) begin
            plain_q2 <= plain_q;
            gam_q2   <= gam_q;
            pix_q2   <= pix_q;
            refo_q2  <= ref_q;
        end
    function automatic [31:0] rev_bytes_bits(input [31:0] v);
        integer i;
        begin
            for (i = 0; i < 32; i = i + 1)
                rev_bytes_bits[i] = v[(i & ~7) + (7 - (i & 7))];
        end
    endfunction
    reg [31:0] b_data;  // left-aligned, zero past b_len
    always @(*) begin
        case (b2_src)
            B_HDR:   b_data = {o_hdr_flags, o_hdr_seq, 16'd0};
            B_PLAIN: b_data = o_raw ? rev_bytes_bits(plain_q2) : plain_q2;
            B_GAM:   b_data = gam_q2;
            B_PIX:   b_data = pix_q2;
            default: b_data = refo_q2[16] ? {refo_q2[7:0], refo_q2[15:8], 16'd0} : 32'd0;
        endcase
    end

    // The selected item, registered (the RAMs' read data goes through one mux, not into the
    // shifter).
    reg        m_valid, m_flush;
    reg [5:0]  m_len;
    reg [31:0] m_data;

    reg  [63:0] oacc;
    reg  [4:0]  ofill;
    wire [63:0] omerged = oacc | ({m_data, 32'd0} >> ofill);
    wire [5:0]  ototal  = {1'b0, ofill} + m_len;

    // =====================================================================================
    // Control
    // =====================================================================================
    always @(posedge clk) begin
        if (rst) begin
            state     <= S_IDLE;
            present   <= 1'b0;
            kreg      <= 16'd0;
            budget    <= 16'd0;
            seq       <= 8'd0;
            fill_mode <= 1'b1;
            out_valid <= 1'b0;
            out_last  <= 1'b0;
            out_len   <= 16'd0;
            out_data  <= 32'd0;
            b_valid   <= 1'b0;
            m_valid   <= 1'b0;
            b2_valid  <= 1'b0;
        end else begin
            case (state)
                S_IDLE: begin
                    if (cmd_valid) begin
                        case (cmd_op)
                            2'd0: begin
                                kreg <= cmd_k;
                                if (cmd_k == 16'd0) budget <= 16'd0;
                                else if (budget > cmd_k - 16'd1) budget <= cmd_k - 16'd1;
                            end
                            2'd1: present <= 1'b0;
                            2'd2: begin
                                present <= 1'b0;
                                seq     <= 8'd0;
                                budget  <= 16'd0;
                                kreg    <= cmd_k;
                            end
                            default: ;
                        endcase
                    end else if (in_valid) begin
                        wreg  <= width;
                        wlast <= width - 14'd1;
                        pred  <= present && (kreg == 16'd0 || budget != 16'd0);
                        col   <= 13'd0;
                        state <= S_PREP;
                    end
                end
                S_PREP:  state <= S_PREP1;
                S_PREP1: state <= S_RUN;
                S_RUN: if (adv) begin
                    col <= col + 13'd1;
                    if (last) begin
                        dcnt  <= 4'd0;
                        state <= S_DRAIN;
                    end
                end
                S_DRAIN: begin
                    dcnt <= dcnt + 4'd1;
                    if (dcnt == 4'd11) state <= S_DECIDE0;
                end
                S_DECIDE0: state <= S_DECIDE;
                S_DECIDE: begin
                    o_raw        <= raw;
                    o_hdr_flags  <= raw ? 8'h02 : {5'd0, d_plain, 1'b0, pred};
                    o_hdr_seq    <= seq;
                    o_vsrc_plain <= raw || d_plain;
                    if (raw || d_plain) begin
                        o_nvm1  <= {5'd0, wm1[13:5]};
                        o_vlast <= raw ? (({1'b0, wm1[4:0]} + 6'd8) & 6'h38)
                                       : ({1'b0, wm1[4:0]} + 6'd1);
                    end else begin
                        o_nvm1  <= {5'd0, vm1[13:5]};
                        o_vlast <= {1'b0, vm1[4:0]} + 6'd1;
                    end
                    o_npm1   <= raw ? wm1 : pm1[18:5];
                    o_np0    <= !raw && pbits == 20'd0;
                    o_plast  <= {1'b0, pm1[4:0]} + 6'd1;
                    out_len  <= plen[15:0];
                    o_nwm1   <= plen[15:2] + {13'd0, plen[1:0] != 2'd0} - 14'd1;
                    owc      <= 14'd0;
                    oacc     <= 64'd0;
                    ofill    <= 5'd0;
                    b_valid  <= 1'b0;
                    m_valid  <= 1'b0;
                    b2_valid <= 1'b0;
                    ophase   <= O_HDR;
                    oidx     <= 14'd0;
                    // The Encoder's bookkeeping.
                    seq       <= seq + 8'd1;
                    present   <= 1'b1;
                    fill_mode <= raw || !pred;
                    if (pred && !raw) budget <= (budget == 16'd0) ? 16'd0 : budget - 16'd1;
                    else              budget <= (kreg == 16'd0) ? 16'd0 : kreg - 16'd1;
                    state <= S_OUT;
                end
                S_OUT: begin
                    if (out_valid && out_ready && out_last) begin
                        out_valid <= 1'b0;
                        out_last  <= 1'b0;
                        state     <= S_IDLE;
                    end else if (oadv) begin
                        // Items: issue (the RAM reads above) and register.
                        b_valid <= it_valid;
                        b_flush <= it_flush;
                        b_src   <= it_src;
                        b_len   <= it_len;
                        ophase  <= ophase_n;
                        oidx    <= oidx_n;
                        b2_valid <= b_valid;
                        b2_flush <= b_flush;
                        b2_src   <= b_src;
                        b2_len   <= b_len;
                        m_valid <= b2_valid;
                        m_flush <= b2_flush;
                        m_len   <= b2_len;
                        m_data  <= b_data;
                        // Merge the item selected last clock.
                        out_valid <= 1'b0;
                        if (m_valid && !m_flush) begin
                            if (ototal[5]) begin
                                out_valid <= 1'b1;
                                out_data  <= {omerged[39:32], omerged[47:40],
                                              omerged[55:48], omerged[63:56]};
                                out_last  <= (owc == o_nwm1);
                                owc       <= owc + 14'd1;
                                oacc      <= {omerged[31:0], 32'd0};
                            end else begin
                                oacc <= omerged;
                            end
                            ofill <= ototal[4:0];
                        end else if (m_valid && m_flush && ofill != 5'd0) begin
                            out_valid <= 1'b1;
                            out_data  <= {oacc[39:32], oacc[47:40], oacc[55:48], oacc[63:56]};
                            out_last  <= (owc == o_nwm1);
                            owc       <= owc + 14'd1;
                            ofill     <= 5'd0;
                        end
                    end
                end
                default: state <= S_IDLE;
            endcase
        end
    end
endmodule

`default_nettype wire
