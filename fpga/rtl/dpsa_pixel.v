// dpsa front end: one pixel per clock through the core's per-pixel stages, bit for bit.
//
//   samples x_j --[accumulate]--> V = [v2, v3] --[gate, atan2]--> phi --[height]--> h, flags
//
// Every stage is the integer arithmetic of dpsa-core, step for step, so the outputs equal the
// core's for every input (the co-simulation in fpga/tests checks it):
//   accumulate  core/src/offload.rs  front_end_pixel: v = sum_j q_j x_j, wrapping 32-bit sums,
//               [SATURATED, 0] when a sample x_j (j < n) is >= sat.
//   gate        core/src/height.rs   Gate::modulated: hi >= fast, or C^2 >= thr2 and C^2 != 0,
//               C^2 = v2^2 + v3^2 exact in 64 bits (hi = max(|v2|, |v3|)).
//   atan2       core/src/phase.rs    atan2: normalise by clz(hi), divisor d = (hi << s) >> 16
//               | 0x8000 (16 bits), t = min((lo << s) / d, 2^16) by an 18-stage restoring
//               divider, ATAN table (atan.hex, the core's table) interpolated on t's low byte,
//               octant and quadrant folding in wrapping binary-angle arithmetic.
//   height      core/src/height.rs   Scale::height / ColumnScale::height: D = phi - (rho +
//               ref_phase) wrapping, h = ((D k) >> 32 + half) >> sh, the 32 x 32 product built
//               from four 16 x 16 partial products (one DSP block each).
//
// Formats: x_j u16 DN; q_j i16 with `frac` fractional bits (Coef), v2/v3 i32 in the same units;
// fast u32 and thr2 u64 in those units (Scale::gate); phases u32 binary angles (2^32 a turn);
// k i32 (uniform scale: LSB per turn Q16.16, half = 2^15, sh = 16; per-column scale: the
// mantissa m_c, half = 2^(15 - shift), sh = 16 - shift); h i16 LSB.
//
// The window registers (n .. rho) must hold still while pixels of the window are in the
// pipeline: the MCU writes them between rows (docs/fpga.md). Latency: LATENCY clocks.
`default_nettype none

// Bits the arithmetic drops on purpose (a product's carry-out, a 64-bit product's low word,
// the normalised divisor's low half) are not flagged.
/* verilator lint_off UNUSEDSIGNAL */
module dpsa_pixel #(
    parameter ATAN_HEX = "atan.hex"
) (
    input  wire         clk,
    // Window registers.
    input  wire [3:0]   n,
    input  wire [127:0] q2,
    input  wire [127:0] q3,
    input  wire [15:0]  sat,
    input  wire [31:0]  fast,
    input  wire [63:0]  thr2,
    input  wire [31:0]  half,
    input  wire [4:0]   sh,
    input  wire [31:0]  rho,
    // One pixel per clock.
    input  wire         in_valid,
    input  wire [127:0] x,
    input  wire [31:0]  ref_phase,
    input  wire [31:0]  k,
    // LATENCY clocks later.
    output wire         out_valid,
    output wire [31:0]  v2,
    output wire [31:0]  v3,
    output wire [31:0]  phi,
    output wire [15:0]  h,
    output wire         px_valid,
    output wire         px_saturated,
    output wire         px_low_modulation
);
    localparam LATENCY = 36;
    localparam [31:0] QUARTER = 32'h4000_0000;
    localparam [31:0] HALF = 32'h8000_0000;
    localparam [31:0] SATURATED = 32'h8000_0000;

    // The core's ATAN table: atan(i / 256) in binary-angle units, i = 0..256, and a guard.
    reg [31:0] atan_rom [0:257];
    initial $readmemh(ATAN_HEX, atan_rom);

    // ---- s1..s3: accumulate --------------------------------------------------------------
    reg [31:0] p2_s1 [0:7];
    reg [31:0] p3_s1 [0:7];
    reg        sat_s1;
    reg [31:0] phi_r_s1, k_s1;
    integer j;
    always @(posedge clk) begin
        sat_s1 <= 1'b0;
        for (j = 0; j < 8; j = j + 1) begin
            if (j < n) begin
                // i16 x u16: the 33-bit product, its low 32 bits (the sums wrap anyway).
                p2_s1[j] <= mul_q_x(q2[16*j +: 16], x[16*j +: 16]);
                p3_s1[j] <= mul_q_x(q3[16*j +: 16], x[16*j +: 16]);
                if (x[16*j +: 16] >= sat) sat_s1 <= 1'b1;
            end else begin
                p2_s1[j] <= 32'd0;
                p3_s1[j] <= 32'd0;
            end
        end
        phi_r_s1 <= rho + ref_phase;
        k_s1 <= k;
    end

    function [31:0] mul_q_x(input [15:0] q, input [15:0] xs);
        reg signed [16:0] xe;
        reg signed [32:0] p;
        begin
            xe = {1'b0, xs};
            p = $signed(q) * xe;
            mul_q_x = p[31:0];
        end
    endfunction

    reg [31:0] s2_s2 [0:3];
    reg [31:0] s3_s2 [0:3];
    reg        sat_s2;
    always @(posedge clk) begin
        for (j = 0; j < 4; j = j + 1) begin
            s2_s2[j] <= p2_s1[2*j] + p2_s1[2*j+1];
            s3_s2[j] <= p3_s1[2*j] + p3_s1[2*j+1];
        end
        sat_s2 <= sat_s1;
    end

    reg [31:0] v2_s3, v3_s3;
    always @(posedge clk) begin
        if (sat_s2) begin
            v2_s3 <= SATURATED;
            v3_s3 <= 32'd0;
        end else begin
            v2_s3 <= (s2_s2[0] + s2_s2[1]) + (s2_s2[2] + s2_s2[3]);
            v3_s3 <= (s3_s2[0] + s3_s2[1]) + (s3_s2[2] + s3_s2[3]);
        end
    end

    // ---- s4..s8: magnitudes, the gate, normalisation -------------------------------------
    reg [31:0] ax_s4, ay_s4;
    reg        xneg_s4, yneg_s4, sat_s4;
    always @(posedge clk) begin
        ax_s4 <= v2_s3[31] ? (~v2_s3 + 32'd1) : v2_s3;
        ay_s4 <= v3_s3[31] ? (~v3_s3 + 32'd1) : v3_s3;
        xneg_s4 <= v2_s3[31];
        yneg_s4 <= v3_s3[31];
        sat_s4 <= (v2_s3 == SATURATED);
    end

    // hi, lo, and the squares' 16 x 16 partial products (unsigned).
    reg [31:0] hi_s5, lo_s5;
    reg        swap_s5;
    reg [31:0] xhh_s5, xhl_s5, xll_s5, yhh_s5, yhl_s5, yll_s5;
    always @(posedge clk) begin
        if (ax_s4 >= ay_s4) begin
            hi_s5 <= ax_s4;
            lo_s5 <= ay_s4;
            swap_s5 <= 1'b0;
        end else begin
            hi_s5 <= ay_s4;
            lo_s5 <= ax_s4;
            swap_s5 <= 1'b1;
        end
        xhh_s5 <= ax_s4[31:16] * ax_s4[31:16];
        xhl_s5 <= ax_s4[31:16] * ax_s4[15:0];
        xll_s5 <= ax_s4[15:0] * ax_s4[15:0];
        yhh_s5 <= ay_s4[31:16] * ay_s4[31:16];
        yhl_s5 <= ay_s4[31:16] * ay_s4[15:0];
        yll_s5 <= ay_s4[15:0] * ay_s4[15:0];
    end

    function [5:0] clz32(input [31:0] v);
        integer b;
        reg found;
        begin
            clz32 = 6'd32;
            found = 1'b0;
            for (b = 31; b >= 0; b = b - 1) begin
                if (!found && v[b]) begin
                    clz32 = 6'd31 - b[5:0];
                    found = 1'b1;
                end
            end
        end
    endfunction

    reg [5:0]  s_s6;
    reg [31:0] hi_s6, lo_s6;
    reg [63:0] sqx_s6, sqy_s6;
    reg        fast_s6;
    always @(posedge clk) begin
        s_s6 <= clz32(hi_s5);
        hi_s6 <= hi_s5;
        lo_s6 <= lo_s5;
        sqx_s6 <= {xhh_s5, 32'd0} + {15'd0, xhl_s5, 17'd0} + {32'd0, xll_s5};
        sqy_s6 <= {yhh_s5, 32'd0} + {15'd0, yhl_s5, 17'd0} + {32'd0, yll_s5};
        fast_s6 <= hi_s5 >= fast;
    end

    // (0, 0): s = 32, which the core's wrapping shift takes as a shift by 0.
    reg [31:0] hn_s7, ln_s7;
    reg [63:0] c2_s7;
    reg        fast_s7;
    always @(posedge clk) begin
        hn_s7 <= hi_s6 << s_s6[4:0];
        ln_s7 <= lo_s6 << s_s6[4:0];
        c2_s7 <= sqx_s6 + sqy_s6;
        fast_s7 <= fast_s6;
    end

    // Divisor d in [2^15, 2^16); the dividend's top 14 bits are below d, so the quotient has
    // 18 bits and the divider starts there.
    reg [15:0] d_s8;
    reg [15:0] rem_s8;
    reg [17:0] bits_s8;
    reg        mod_s8;
    always @(posedge clk) begin
        d_s8 <= hn_s7[31:16] | 16'h8000;
        rem_s8 <= {2'b00, ln_s7[31:18]};
        bits_s8 <= ln_s7[17:0];
        mod_s8 <= fast_s7 || (c2_s7 >= thr2 && c2_s7 != 64'd0);
    end

    // ---- s9..s26: t = (lo << s) / d, one quotient bit a stage ------------------------------
    reg [15:0] div_d   [0:17];
    reg [15:0] div_rem [0:17];
    reg [17:0] div_bits[0:17];
    reg [17:0] div_q   [0:17];
    genvar g;
    generate
        for (g = 0; g < 18; g = g + 1) begin : divider
            wire [15:0] d_in;
            wire [15:0] r_in;
            wire [17:0] b_in;
            wire [17:0] q_in;
            if (g == 0) begin : first
                assign d_in = d_s8;
                assign r_in = rem_s8;
                assign b_in = bits_s8;
                assign q_in = 18'd0;
            end else begin : next
                assign d_in = div_d[g-1];
                assign r_in = div_rem[g-1];
                assign b_in = div_bits[g-1];
                assign q_in = div_q[g-1];
            end
            wire [16:0] r = {r_in, b_in[17]};
            wire ge = r >= {1'b0, d_in};
            wire [16:0] r_sub = r - {1'b0, d_in};
            always @(posedge clk) begin
                div_d[g] <= d_in;
                div_rem[g] <= ge ? r_sub[15:0] : r[15:0];
                div_bits[g] <= {b_in[16:0], 1'b0};
                div_q[g] <= {q_in[16:0], ge};
            end
        end
    endgenerate
    wire [17:0] q_s26 = div_q[17];

    // ---- s27..s31: table, interpolation, folding -----------------------------------------
    reg [16:0] t_s27;
    always @(posedge clk) t_s27 <= (q_s26 > 18'd65536) ? 17'd65536 : q_s26[16:0];

    reg [31:0] a_s28, b_s28;
    reg [7:0]  f_s28;
    always @(posedge clk) begin
        a_s28 <= atan_rom[t_s27[16:8]];
        b_s28 <= atan_rom[t_s27[16:8] + 9'd1];
        f_s28 <= t_s27[7:0];
    end

    reg [31:0] a_s29, prod_s29;
    always @(posedge clk) begin
        a_s29 <= a_s28;
        prod_s29 <= (b_s28 - a_s28) * {24'd0, f_s28};
    end

    reg [31:0] oct_s30;
    always @(posedge clk) oct_s30 <= a_s29 + ((prod_s29 + 32'd128) >> 8);

    wire swap_s30, xneg_s30, yneg_s30;
    dpsa_delay #(.W(1), .D(25)) dl_swap (.clk(clk), .d(swap_s5), .q(swap_s30));
    dpsa_delay #(.W(2), .D(26)) dl_sign (.clk(clk), .d({xneg_s4, yneg_s4}), .q({xneg_s30, yneg_s30}));

    reg [31:0] ang_s31;
    always @(posedge clk) begin : fold
        reg [31:0] a0, a1;
        a0 = swap_s30 ? (QUARTER - oct_s30) : oct_s30;
        a1 = xneg_s30 ? (HALF - a0) : a0;
        ang_s31 <= yneg_s30 ? (32'd0 - a1) : a1;
    end

    // ---- s32..s36: height ------------------------------------------------------------------
    wire [31:0] phi_r_s31, k_s32;
    dpsa_delay #(.W(32), .D(30)) dl_phi_r (.clk(clk), .d(phi_r_s1), .q(phi_r_s31));
    dpsa_delay #(.W(32), .D(31)) dl_k (.clk(clk), .d(k_s1), .q(k_s32));

    reg [31:0] dd_s32;
    always @(posedge clk) dd_s32 <= ang_s31 - phi_r_s31;

    // D k, both signed: D = dh 2^16 + dl, k = kh 2^16 + kl (dh, kh signed; dl, kl unsigned).
    reg signed [31:0] hh_s33, hl_s33, lh_s33;
    reg [31:0] ll_s33;
    always @(posedge clk) begin
        hh_s33 <= $signed(dd_s32[31:16]) * $signed(k_s32[31:16]);
        hl_s33 <= $signed(dd_s32[31:16]) * $signed({1'b0, k_s32[15:0]});
        lh_s33 <= $signed({1'b0, dd_s32[15:0]}) * $signed(k_s32[31:16]);
        ll_s33 <= dd_s32[15:0] * k_s32[15:0];
    end

    reg signed [33:0] mid_s34;
    reg signed [31:0] hh_s34;
    reg [31:0] ll_s34;
    always @(posedge clk) begin
        mid_s34 <= {{2{hl_s33[31]}}, hl_s33} + {{2{lh_s33[31]}}, lh_s33};
        hh_s34 <= hh_s33;
        ll_s34 <= ll_s33;
    end

    reg [63:0] dk_s35;
    always @(posedge clk)
        dk_s35 <= {hh_s34, 32'd0} + {{14{mid_s34[33]}}, mid_s34, 16'd0} + {32'd0, ll_s34};

    wire [31:0] r_s35 = dk_s35[63:32] + half;
    wire [31:0] h_s35 = $signed(r_s35) >>> sh;
    reg [15:0] h_s36;
    always @(posedge clk) h_s36 <= h_s35[15:0];

    // ---- side band to the output --------------------------------------------------------------
    wire [31:0] phi_s36;
    dpsa_delay #(.W(32), .D(LATENCY - 31)) dl_phi (.clk(clk), .d(ang_s31), .q(phi_s36));
    wire [63:0] v_s36;
    wire sat_s36, mod_s36;
    dpsa_delay #(.W(64), .D(LATENCY - 3)) dl_v (.clk(clk), .d({v2_s3, v3_s3}), .q(v_s36));
    dpsa_delay #(.W(1), .D(LATENCY - 4)) dl_sat (.clk(clk), .d(sat_s4), .q(sat_s36));
    dpsa_delay #(.W(1), .D(LATENCY - 8)) dl_mod (.clk(clk), .d(mod_s8), .q(mod_s36));
    dpsa_delay #(.W(1), .D(LATENCY)) dl_valid (.clk(clk), .d(in_valid), .q(out_valid));

    assign v2 = v_s36[63:32];
    assign v3 = v_s36[31:0];
    assign phi = phi_s36;
    assign h = h_s36;
    assign px_saturated = sat_s36;
    assign px_valid = !sat_s36 && mod_s36;
    assign px_low_modulation = !sat_s36 && !mod_s36;
endmodule
/* verilator lint_on UNUSEDSIGNAL */

`default_nettype wire
