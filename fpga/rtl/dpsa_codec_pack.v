// dpsa_codec_pack: an MSB-first bit packer for the row codec's encoder (dpsa_codec.v).
//
// Appends up to 32 bits a clock (the low `in_len` bits of `in_bits`, whose bits at and above
// `in_len` must be 0) to a 64-bit left-aligned accumulator and hands every completed 32-bit
// word to the parent (we / waddr / wdata; the first bit of the stream is bit 31 of word 0).
// Two stages: the bits are left-aligned into a register, then merged; a completed word is
// presented one clock after the merge, two after the input. `flush` hands over the partial
// last word (zero padded) if there is one. `nbits` counts every bit appended since `clr`, including
// those of words the parent may not store (it bounds its buffer): it is the section's length.
//
// `flush` acts in the merge stage: the parent asserts it once the last append has been merged
// (two clocks after the last in_valid at the earliest), and not before: an append still in the
// align register would be lost.
`default_nettype none

module dpsa_codec_pack (
    input  wire        clk,
    input  wire        clr,       // start a new section: empty, word 0, count 0
    input  wire        in_valid,
    input  wire [31:0] in_bits,
    input  wire [5:0]  in_len,    // 0 ..= 32
    input  wire        flush,
    output reg         we,
    output reg  [12:0] waddr,
    output reg  [31:0] wdata,
    output reg  [19:0] nbits
);
    reg  [63:0] acc;   // pending bits, left-aligned (bit 63 first)
    reg  [4:0]  fill;  // pending bits, 0 ..= 31
    reg  [12:0] widx;  // index of the next word

    // Stage 1: the new bits left-aligned in 32.
    reg         l_valid;
    reg  [31:0] l_bits;
    reg  [5:0]  l_len;
    always @(posedge clk) begin
        l_valid <= in_valid && !clr;
        l_bits  <= (in_len == 6'd0) ? 32'd0 : (in_bits << (6'd32 - in_len));
        l_len   <= in_len;
    end

    // Stage 2: placed right after the pending bits.
    wire [63:0] merged = acc | ({l_bits, 32'd0} >> fill);
    wire [5:0]  total  = {1'b0, fill} + l_len;

    always @(posedge clk) begin
        we <= 1'b0;
        if (clr) begin
            acc   <= 64'd0;
            fill  <= 5'd0;
            widx  <= 13'd0;
            nbits <= 20'd0;
        end else if (l_valid) begin
            nbits <= nbits + {14'd0, l_len};
            if (total[5]) begin
                we    <= 1'b1;
                waddr <= widx;
                wdata <= merged[63:32];
                widx  <= widx + 13'd1;
                acc   <= {merged[31:0], 32'd0};
            end else begin
                acc <= merged;
            end
            fill <= total[4:0];
        end else if (flush && fill != 5'd0) begin
            we    <= 1'b1;
            waddr <= widx;
            wdata <= acc[63:32];
            widx  <= widx + 13'd1;
            acc   <= 64'd0;
            fill  <= 5'd0;
        end
    end
endmodule

`default_nettype wire
