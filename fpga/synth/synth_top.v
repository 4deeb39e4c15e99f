// Synthesis/timing harness for dpsa_pixel on a pin-limited FPGA.
//
// Not a functional top level: it exists so that place-and-route sees the
// real datapath with register-to-register timing and nothing folded away.
//
//  * Window registers (n, q2, q3, sat, fast, thr2, half, sh, rho) are
//    flip-flops written over a small register bus (addr/wdata/we), as the
//    MCU would write them between rows. WIN_PER_LANE = 0: one set shared by
//    all lanes; 1: one set per lane, each written when its bit of the lane
//    mask register (address 16) is set, so the copies are distinct FFs.
//    With one shared set, each lane reads it through its own registered copy
//    (kept: synthesis must not merge the copies), so the set's fan-out is one
//    register per lane and each copy can sit beside its lane. The copy adds a
//    clock between a bus write and the lane, which the MCU's writes between
//    rows absorb.
//  * Pixel inputs (x, ref_phase, k) of each lane come from a 192-bit
//    scrambler register of that lane: every clock each bit is loaded with the
//    XOR of two other state bits and one (registered) wdata pin, so all pixel
//    inputs are fresh, non-constant register outputs each cycle. It is not a
//    plain shift register on purpose: no input bit is a pure delay of another
//    or of a pin, so synthesis cannot merge the datapath's delay lines into it
//    or fold one lane's registers into another's.
//  * All outputs of all lanes are captured in flip-flops and XOR-folded
//    into OUT_W registered output pins, so every output bit is observable.
//
// Parameter LANES: number of dpsa_pixel instances in parallel (pixels/clock).
module dpsa_synth_top #(
  parameter LANES = 2,
  parameter WIN_PER_LANE = 0,
  parameter OUT_W = 8
) (
  input  wire             clk,
  input  wire [4:0]       addr,
  input  wire [31:0]      wdata,
  input  wire             we,
  input  wire             pix_valid,
  output reg  [OUT_W-1:0] dout
);
  // ---- register bus: input pins are registered first ----------------------
  reg [4:0]  addr_q;
  reg [31:0] wdata_q;
  reg        we_q, valid_q;
  always @(posedge clk) begin
    addr_q  <= addr;
    wdata_q <= wdata;
    we_q    <= we;
    valid_q <= pix_valid;
  end

  // ---- window registers ----------------------------------------------------
  // 0: n   1..4: q2   5..8: q3   9: sat   10: fast   11..12: thr2
  // 13: half   14: sh   15: rho   16: lane mask (WIN_PER_LANE = 1 only)
  localparam NWIN = WIN_PER_LANE ? LANES : 1;
  reg [LANES-1:0] lane_mask;
  always @(posedge clk)
    if (we_q && addr_q == 5'd16) lane_mask <= wdata_q[LANES-1:0];

  // All window bits of set c, packed: {n, q2, q3, sat, fast, thr2, half, sh, rho}.
  localparam WIN_W = 4 + 128 + 128 + 16 + 32 + 64 + 32 + 5 + 32;
  wire [WIN_W*NWIN-1:0] win_all;

  genvar c;
  generate
    for (c = 0; c < NWIN; c = c + 1) begin : win
      wire wr = we_q && (WIN_PER_LANE ? lane_mask[c] : 1'b1);
      reg [3:0]   n_r;
      reg [127:0] q2_r, q3_r;
      reg [15:0]  sat_r;
      reg [31:0]  fast_r;
      reg [63:0]  thr2_r;
      reg [31:0]  half_r;
      reg [4:0]   sh_r;
      reg [31:0]  rho_r;
      always @(posedge clk) begin
        if (wr) begin
          case (addr_q)
            5'd0:  n_r           <= wdata_q[3:0];
            5'd1:  q2_r[31:0]    <= wdata_q;
            5'd2:  q2_r[63:32]   <= wdata_q;
            5'd3:  q2_r[95:64]   <= wdata_q;
            5'd4:  q2_r[127:96]  <= wdata_q;
            5'd5:  q3_r[31:0]    <= wdata_q;
            5'd6:  q3_r[63:32]   <= wdata_q;
            5'd7:  q3_r[95:64]   <= wdata_q;
            5'd8:  q3_r[127:96]  <= wdata_q;
            5'd9:  sat_r         <= wdata_q[15:0];
            5'd10: fast_r        <= wdata_q;
            5'd11: thr2_r[31:0]  <= wdata_q;
            5'd12: thr2_r[63:32] <= wdata_q;
            5'd13: half_r        <= wdata_q;
            5'd14: sh_r          <= wdata_q[4:0];
            5'd15: rho_r         <= wdata_q;
            default: ;
          endcase
        end
      end
      assign win_all[WIN_W*c +: WIN_W] =
        {n_r, q2_r, q3_r, sat_r, fast_r, thr2_r, half_r, sh_r, rho_r};
    end
  endgenerate

  // ---- pixel inputs: per-lane scramblers fed from the pins every clock -----
  localparam PIX_W = 128 + 32 + 32;            // x, ref_phase, k per lane

  // ---- lanes -----------------------------------------------------------------
  localparam OUT_PER_LANE = 1 + 32 + 32 + 16 + 3;
  wire [OUT_PER_LANE*LANES-1:0] lane_out;

  genvar l;
  generate
    for (l = 0; l < LANES; l = l + 1) begin : lane
      // the window register set of this lane
      wire [3:0]   n;    wire [127:0] q2, q3; wire [15:0] sat; wire [31:0] fast;
      wire [63:0]  thr2; wire [31:0] half;    wire [4:0]  sh;  wire [31:0] rho;
      wire [WIN_W-1:0] win_l;
      if (WIN_PER_LANE) begin : own
        assign win_l = win_all[WIN_W*l +: WIN_W];
      end else begin : copy
        reg [WIN_W-1:0] win_r;
        (* keep *) always @(posedge clk) win_r <= win_all[0 +: WIN_W];
        assign win_l = win_r;
      end
      assign {n, q2, q3, sat, fast, thr2, half, sh, rho} = win_l;
      reg [PIX_W-1:0] px;
      integer i;
      always @(posedge clk)
        for (i = 0; i < PIX_W; i = i + 1)
          px[i] <= px[(i + 1) % PIX_W] ^ px[(i + 97 + 2 * l) % PIX_W]
                   ^ wdata_q[(i + 7 * l) % 32];
      wire        out_valid, px_valid, px_saturated, px_low_modulation;
      wire [31:0] v2, v3;
      wire [15:0] h;
      dpsa_pixel u_pixel (
        .clk(clk),
        .n(n), .q2(q2), .q3(q3), .sat(sat), .fast(fast),
        .thr2(thr2), .half(half), .sh(sh), .rho(rho),
        .in_valid(valid_q),
        .x(px[127:0]), .ref_phase(px[159:128]), .k(px[191:160]),
        .out_valid(out_valid), .v2(v2), .v3(v3), .h(h),
        .px_valid(px_valid), .px_saturated(px_saturated),
        .px_low_modulation(px_low_modulation)
      );
      assign lane_out[OUT_PER_LANE*l +: OUT_PER_LANE] =
        {out_valid, v2, v3, h, px_valid, px_saturated, px_low_modulation};
    end
  endgenerate

  // ---- outputs: capture in flip-flops, then XOR-fold onto OUT_W pins ---------
  localparam OUT_BITS = OUT_PER_LANE * LANES;
  localparam FOLD_N   = (OUT_BITS + OUT_W - 1) / OUT_W;
  reg  [FOLD_N*OUT_W-1:0] out_q;
  always @(posedge clk)
    out_q <= {{(FOLD_N*OUT_W-OUT_BITS){1'b0}}, lane_out};

  integer b;
  reg [OUT_W-1:0] fold;
  always @* begin
    fold = {OUT_W{1'b0}};
    for (b = 0; b < FOLD_N; b = b + 1)
      fold = fold ^ out_q[OUT_W*b +: OUT_W];
  end
  always @(posedge clk)
    dout <= fold;
endmodule
