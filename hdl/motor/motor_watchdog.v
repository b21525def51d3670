// Command watchdog (thesis 6.3): brake when the host has been silent for longer than the timeout.
// A microsecond prescaler (CLK_PER_US clocks) drives a microsecond counter that every accepted
// command (kick) clears. expired is 1 from reset until the first kick, and from timeout_us
// microseconds after the last kick (within one clock) until the next one.
module motor_watchdog #(
    parameter CLK_PER_US = 50  // board clock 50 MHz
) (
    input wire clk,
    input wire rst,
    input wire kick,
    input wire [23:0] timeout_us,  // 10000 = 10 ms; 0 would brake at once
    output reg expired,
    output reg [15:0] trips  // ok -> expired transitions (diagnostics)
);
    localparam PW = (CLK_PER_US > 1) ? $clog2(CLK_PER_US) : 1;
    reg [PW-1:0] prescale;
    reg [23:0] elapsed_us;

    wire us_tick = (prescale == CLK_PER_US - 1);

    always @(posedge clk) begin
        if (rst) begin
            prescale <= 0;
            elapsed_us <= 0;
            expired <= 1'b1;
            trips <= 0;
        end else if (kick) begin
            prescale <= 0;
            elapsed_us <= 0;
            expired <= 1'b0;
        end else begin
            prescale <= us_tick ? {PW{1'b0}} : prescale + 1'b1;
            if (us_tick && !expired) begin
                elapsed_us <= elapsed_us + 1'b1;
                if (elapsed_us + 1'b1 >= timeout_us) begin
                    expired <= 1'b1;
                    trips <= trips + 1'b1;
                end
            end
        end
    end
endmodule
