// Synthesis/timing wrapper for dpsa_codec (the row codec's encoder) on a pin-limited FPGA.
//
// Not a functional top level: it gives place-and-route the real encoder with
// register-to-register timing and nothing folded away, through a few pins.
//
//  * The width register and the commands come from registered pins (we[0]
//    loads width from wdata, we[1] issues command `op` with cmd_k = wdata).
//  * The pixels (height and validity) come from a 32-bit LFSR mixed with the
//    registered wdata pins, so every input bit is a fresh register output;
//    in_valid is the registered `go` pin.
//  * out_ready is a registered pin; the output word, length and flags are
//    XOR-folded into 8 registered output pins.
module dpsa_codec_synth_top (
  input  wire        clk,
  input  wire        rst,
  input  wire [15:0] wdata,
  input  wire [1:0]  we,
  input  wire [1:0]  op,
  input  wire        go,
  input  wire        ready,
  output reg  [7:0]  dout,
  output reg         busy
);
  reg [15:0] wdata_q;
  reg [1:0]  we_q, op_q;
  reg        go_q, ready_q, rst_q;
  reg [13:0] width;
  reg [31:0] lfsr;
  always @(posedge clk) begin
    wdata_q <= wdata;
    we_q    <= we;
    op_q    <= op;
    go_q    <= go;
    ready_q <= ready;
    rst_q   <= rst;
    if (we_q[0]) width <= wdata_q[13:0];
    lfsr <= rst_q ? 32'h1 : {lfsr[30:0], lfsr[31] ^ lfsr[21] ^ lfsr[1] ^ lfsr[0]};
  end

  wire        cmd_ready, in_ready, out_valid, out_last;
  wire [31:0] out_data;
  wire [15:0] out_len;
  dpsa_codec enc (
    .clk(clk), .rst(rst_q),
    .cmd_valid(we_q[1]), .cmd_ready(cmd_ready), .cmd_op(op_q), .cmd_k(wdata_q),
    .width(width),
    .in_valid(go_q), .in_ready(in_ready), .in_h(lfsr[15:0] ^ wdata_q), .in_v(lfsr[16] | lfsr[23]),
    .out_valid(out_valid), .out_ready(ready_q), .out_data(out_data), .out_last(out_last),
    .out_len(out_len)
  );

  always @(posedge clk) begin
    dout <= out_data[7:0] ^ out_data[15:8] ^ out_data[23:16] ^ out_data[31:24]
            ^ out_len[7:0] ^ out_len[15:8] ^ {6'd0, out_valid, out_last};
    busy <= ~cmd_ready ^ in_ready;
  end
endmodule
