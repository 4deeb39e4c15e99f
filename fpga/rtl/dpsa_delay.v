// A W-bit signal delayed by D clocks (D >= 1): the side band that travels beside a pipeline.
`default_nettype none

module dpsa_delay #(
    parameter W = 1,
    parameter D = 1
) (
    input  wire         clk,
    input  wire [W-1:0] d,
    output wire [W-1:0] q
);
    reg [W-1:0] stage [0:D-1];
    integer i;
    always @(posedge clk) begin
        stage[0] <= d;
        for (i = 1; i < D; i = i + 1) stage[i] <= stage[i-1];
    end
    assign q = stage[D-1];
endmodule

`default_nettype wire
