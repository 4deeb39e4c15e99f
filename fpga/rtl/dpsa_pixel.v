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
// pipeline: the MCU writes them between rows (docs/fpga.md). Latency: LATENCY (38) clocks;
// stage sN registers its results N clocks after the pixel enters (s1 registers the inputs).
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
    localparam LATENCY = 38;
    localparam [31:0] SATURATED = 32'h8000_0000;

    // The core's ATAN table: atan(i / 256) in binary-angle units, i = 0..256, and a guard.
    reg [31:0] atan_rom [0:257];
    initial $readmemh(ATAN_HEX, atan_rom);

    // ---- s1: the pixel's inputs registered ------------------------------------------------
    // The products of s2 (DSP blocks) start at registers of this module, free to sit beside
    // them, not at the caller's logic.
    reg [127:0] x_s1;
    reg [31:0]  ref_phase_s1, k_in_s1;
    always @(posedge clk) begin
        x_s1 <= x;
        ref_phase_s1 <= ref_phase;
        k_in_s1 <= k;
    end

    // ---- s2..s4: accumulate --------------------------------------------------------------
    reg [31:0] p2_s2 [0:7];
    reg [31:0] p3_s2 [0:7];
    reg        sat_s2;
    reg [31:0] phi_r_s2, k_s2;
    integer j;
    always @(posedge clk) begin
        sat_s2 <= 1'b0;
        for (j = 0; j < 8; j = j + 1) begin
            if (j < n) begin
                // i16 x u16: the 33-bit product, its low 32 bits (the sums wrap anyway).
                p2_s2[j] <= mul_q_x(q2[16*j +: 16], x_s1[16*j +: 16]);
                p3_s2[j] <= mul_q_x(q3[16*j +: 16], x_s1[16*j +: 16]);
                if (x_s1[16*j +: 16] >= sat) sat_s2 <= 1'b1;
            end else begin
                p2_s2[j] <= 32'd0;
                p3_s2[j] <= 32'd0;
            end
        end
        phi_r_s2 <= rho + ref_phase_s1;
        k_s2 <= k_in_s1;
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

    reg [31:0] s2_s3 [0:3];
    reg [31:0] s3_s3 [0:3];
    reg        sat_s3;
    always @(posedge clk) begin
        for (j = 0; j < 4; j = j + 1) begin
            s2_s3[j] <= p2_s2[2*j] + p2_s2[2*j+1];
            s3_s3[j] <= p3_s2[2*j] + p3_s2[2*j+1];
        end
        sat_s3 <= sat_s2;
    end

    reg [31:0] v2_s4, v3_s4;
    always @(posedge clk) begin
        if (sat_s3) begin
            v2_s4 <= SATURATED;
            v3_s4 <= 32'd0;
        end else begin
            v2_s4 <= (s2_s3[0] + s2_s3[1]) + (s2_s3[2] + s2_s3[3]);
            v3_s4 <= (s3_s3[0] + s3_s3[1]) + (s3_s3[2] + s3_s3[3]);
        end
    end

    // ---- s5..s9: magnitudes, the gate, normalisation -------------------------------------
    reg [31:0] ax_s5, ay_s5;
    reg        xneg_s5, yneg_s5, sat_s5;
    always @(posedge clk) begin
        ax_s5 <= v2_s4[31] ? (~v2_s4 + 32'd1) : v2_s4;
        ay_s5 <= v3_s4[31] ? (~v3_s4 + 32'd1) : v3_s4;
        xneg_s5 <= v2_s4[31];
        yneg_s5 <= v3_s4[31];
        sat_s5 <= (v2_s4 == SATURATED);
    end

    // hi, lo, and the squares' 16 x 16 partial products (unsigned).
    reg [31:0] hi_s6, lo_s6;
    reg        swap_s6;
    reg [31:0] xhh_s6, xhl_s6, xll_s6, yhh_s6, yhl_s6, yll_s6;
    always @(posedge clk) begin
        if (ax_s5 >= ay_s5) begin
            hi_s6 <= ax_s5;
            lo_s6 <= ay_s5;
            swap_s6 <= 1'b0;
        end else begin
            hi_s6 <= ay_s5;
            lo_s6 <= ax_s5;
            swap_s6 <= 1'b1;
        end
        xhh_s6 <= ax_s5[31:16] * ax_s5[31:16];
        xhl_s6 <= ax_s5[31:16] * ax_s5[15:0];
        xll_s6 <= ax_s5[15:0] * ax_s5[15:0];
        yhh_s6 <= ay_s5[31:16] * ay_s5[31:16];
        yhl_s6 <= ay_s5[31:16] * ay_s5[15:0];
        yll_s6 <= ay_s5[15:0] * ay_s5[15:0];
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

    reg [5:0]  s_s7;
    reg [31:0] hi_s7, lo_s7;
    reg [63:0] sqx_s7, sqy_s7;
    reg        fast_s7;
    always @(posedge clk) begin
        s_s7 <= clz32(hi_s6);
        hi_s7 <= hi_s6;
        lo_s7 <= lo_s6;
        sqx_s7 <= {xhh_s6, 32'd0} + {15'd0, xhl_s6, 17'd0} + {32'd0, xll_s6};
        sqy_s7 <= {yhh_s6, 32'd0} + {15'd0, yhl_s6, 17'd0} + {32'd0, yll_s6};
        fast_s7 <= hi_s6 >= fast;
    end

    // (0, 0): s = 32, which the core's wrapping shift takes as a shift by 0.
    reg [31:0] hn_s8, ln_s8;
    reg [63:0] c2_s8;
    reg        fast_s8;
    always @(posedge clk) begin
        hn_s8 <= hi_s7 << s_s7[4:0];
        ln_s8 <= lo_s7 << s_s7[4:0];
        c2_s8 <= sqx_s7 + sqy_s7;
        fast_s8 <= fast_s7;
    end

    // Divisor d in [2^15, 2^16); the dividend's top 14 bits are below d, so the quotient has
    // 18 bits and the divider starts there.
    reg [15:0] d_s9;
    reg [15:0] rem_s9;
    reg [17:0] bits_s9;
    reg        mod_s9;
    always @(posedge clk) begin
        d_s9 <= hn_s8[31:16] | 16'h8000;
        rem_s9 <= {2'b00, ln_s8[31:18]};
        bits_s9 <= ln_s8[17:0];
        mod_s9 <= fast_s8 || (c2_s8 >= thr2 && c2_s8 != 64'd0);
    end

    // ---- s10..s27: t = (lo << s) / d, one quotient bit a stage ------------------------------
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
                assign d_in = d_s9;
                assign r_in = rem_s9;
                assign b_in = bits_s9;
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
    wire [17:0] q_s27 = div_q[17];

    // ---- s28..s33: table, interpolation, folding -----------------------------------------
    // s28 clamps t and forms both table addresses; s29 reads the table (a = ATAN[i], b =
    // ATAN[i + 1]); s30 takes b - a; s31 multiplies it by t's low byte f as two partial
    // products (one DSP block each); s32 sums them, rounds and adds a; s33 folds the octant.
    reg [7:0]  f_s28;
    reg [8:0]  ia_s28, ib_s28;
    always @(posedge clk) begin : clamp
        reg [16:0] t;
        t = (q_s27 > 18'd65536) ? 17'd65536 : q_s27[16:0];
        f_s28 <= t[7:0];
        ia_s28 <= t[16:8];
        ib_s28 <= t[16:8] + 9'd1;
    end

    reg [31:0] a_s29, b_s29;
    reg [7:0]  f_s29;
    always @(posedge clk) begin
        a_s29 <= atan_rom[ia_s28];
        b_s29 <= atan_rom[ib_s28];
        f_s29 <= f_s28;
    end

    reg [31:0] a_s30, ba_s30;
    reg [7:0]  f_s30;
    always @(posedge clk) begin
        a_s30 <= a_s29;
        ba_s30 <= b_s29 - a_s29;
        f_s30 <= f_s29;
    end

    // (b - a) f mod 2^32 = (ba_hi f) 2^16 + ba_lo f: only the low 16 bits of the high part.
    reg [31:0] a_s31;
    reg [15:0] ph_s31;
    reg [23:0] pl_s31;
    always @(posedge clk) begin
        a_s31 <= a_s30;
        ph_s31 <= ba_s30[31:16] * {8'd0, f_s30};
        pl_s31 <= ba_s30[15:0] * f_s30;
    end

    wire [31:0] prod_s31 = {ph_s31, 16'd0} + {8'd0, pl_s31};
    reg [31:0] oct_s32;
    always @(posedge clk) oct_s32 <= a_s31 + ((prod_s31 + 32'd128) >> 8);

    wire swap_s32, xneg_s32, yneg_s32;
    dpsa_delay #(.W(1), .D(26)) dl_swap (.clk(clk), .d(swap_s6), .q(swap_s32));
    dpsa_delay #(.W(2), .D(27)) dl_sign (.clk(clk), .d({xneg_s5, yneg_s5}), .q({xneg_s32, yneg_s32}));

    // The three reflections (swap: 2^30 - a; x < 0: 2^31 - a; y < 0: -a) as one adder:
    // ang = +-oct + swap 2^30 + (swap ? yneg : xneg) 2^31 (mod 2^32), the sign
    // swap ^ xneg ^ yneg, and -oct = ~oct + 1.
    reg [31:0] ang_s33;
    always @(posedge clk) begin : fold
        reg neg;
        neg = swap_s32 ^ xneg_s32 ^ yneg_s32;
        ang_s33 <= (oct_s32 ^ {32{neg}})
                 + {swap_s32 ? yneg_s32 : xneg_s32, swap_s32, 29'd0, neg};
    end

    // ---- s34..s38: height ------------------------------------------------------------------
    wire [31:0] phi_r_s33, k_s34;
    dpsa_delay #(.W(32), .D(31)) dl_phi_r (.clk(clk), .d(phi_r_s2), .q(phi_r_s33));
    dpsa_delay #(.W(32), .D(32)) dl_k (.clk(clk), .d(k_s2), .q(k_s34));

    reg [31:0] dd_s34;
    always @(posedge clk) dd_s34 <= ang_s33 - phi_r_s33;

    // D k, both signed: D = dh 2^16 + dl, k = kh 2^16 + kl (dh, kh signed; dl, kl unsigned).
    reg signed [31:0] hh_s35, hl_s35, lh_s35;
    reg [31:0] ll_s35;
    always @(posedge clk) begin
        hh_s35 <= $signed(dd_s34[31:16]) * $signed(k_s34[31:16]);
        hl_s35 <= $signed(dd_s34[31:16]) * $signed({1'b0, k_s34[15:0]});
        lh_s35 <= $signed({1'b0, dd_s34[15:0]}) * $signed(k_s34[31:16]);
        ll_s35 <= dd_s34[15:0] * k_s34[15:0];
    end

    reg signed [33:0] mid_s36;
    reg signed [31:0] hh_s36;
    reg [31:0] ll_s36;
    always @(posedge clk) begin
        mid_s36 <= {{2{hl_s35[31]}}, hl_s35} + {{2{lh_s35[31]}}, lh_s35};
        hh_s36 <= hh_s35;
        ll_s36 <= ll_s35;
    end

    reg [63:0] dk_s37;
    always @(posedge clk)
        dk_s37 <= {hh_s36, 32'd0} + {{14{mid_s36[33]}}, mid_s36, 16'd0} + {32'd0, ll_s36};

    wire [31:0] r_s37 = dk_s37[63:32] + half;
    wire [31:0] h_s37 = $signed(r_s37) >>> sh;
    reg [15:0] h_s38;
    always @(posedge clk) h_s38 <= h_s37[15:0];

    // ---- side band to the output --------------------------------------------------------------
    wire [31:0] phi_s38;
    dpsa_delay #(.W(32), .D(LATENCY - 33)) dl_phi (.clk(clk), .d(ang_s33), .q(phi_s38));
    wire [63:0] v_s38;
    wire sat_s38, mod_s38;
    dpsa_delay #(.W(64), .D(LATENCY - 4)) dl_v (.clk(clk), .d({v2_s4, v3_s4}), .q(v_s38));
    dpsa_delay #(.W(1), .D(LATENCY - 5)) dl_sat (.clk(clk), .d(sat_s5), .q(sat_s38));
    dpsa_delay #(.W(1), .D(LATENCY - 9)) dl_mod (.clk(clk), .d(mod_s9), .q(mod_s38));
    dpsa_delay #(.W(1), .D(LATENCY)) dl_valid (.clk(clk), .d(in_valid), .q(out_valid));

    assign v2 = v_s38[63:32];
    assign v3 = v_s38[31:0];
    assign phi = phi_s38;
    assign h = h_s38;
    assign px_saturated = sat_s38;
    assign px_valid = !sat_s38 && mod_s38;
    assign px_low_modulation = !sat_s38 && !mod_s38;
endmodule
/* verilator lint_on UNUSEDSIGNAL */

`default_nettype wire
