// Centre-aligned (symmetric) 3-phase PWM with dead time, brake, and the current-sampling trigger.
// The counter runs 0, 1, .. P-1, P-1, .. 1, 0, 0, 1 ..: every value twice per period of 2P clocks,
// so a phase with duty d (0..P) has its high side on for exactly 2(d - DEADTIME) clocks, centred on
// the counter peak, which is the centre of the PWM period: the current ripple crosses its mean there,
// so adc_trigger (one clock, the first of the two peak clocks) samples the average phase current.
// Compare values are double-buffered and taken at the valley, so no pulse is ever cut.
// Low side on while cnt < P - d; both sides off for DEADTIME clocks around each switching edge.
// brake: all low sides on, high sides off (windings shorted: the motor brakes by its own back-EMF).
module pwm_center #(
    parameter W = 11,  // counter width; P = period_half < 2^W
    parameter DEADTIME = 10  // clocks (200 ns at 50 MHz)
) (
    input wire clk,
    input wire rst,
    input wire [W-1:0] period_half,  // P: PWM frequency = f_clk / (2P); 1250 -> 20 kHz at 50 MHz
    input wire [W-1:0] duty_a,
    input wire [W-1:0] duty_b,
    input wire [W-1:0] duty_c,
    input wire brake,
    output reg [2:0] hi,  // high-side gates, bit 0 = phase a
    output reg [2:0] lo,  // low-side gates
    output reg adc_trigger,
    output reg period_start  // one clock at the valley, when new duties are taken
);
    reg [W-1:0] cnt;
    reg up;
    reg [W-1:0] da, db, dc;

    function [W-1:0] clamp(input [W-1:0] d);
        clamp = (d > period_half) ? period_half : d;
    endfunction

    // On when cnt >= P - d + DEADTIME, low side when cnt < P - d (W+1 bits: no wrap).
    wire [W:0] th_a = {1'b0, period_half} - {1'b0, da};
    wire [W:0] th_b = {1'b0, period_half} - {1'b0, db};
    wire [W:0] th_c = {1'b0, period_half} - {1'b0, dc};

    always @(posedge clk) begin
        if (rst) begin
            cnt <= 0;
            up <= 1'b1;
            da <= 0;
            db <= 0;
            dc <= 0;
            hi <= 3'b000;
            lo <= 3'b000;
            adc_trigger <= 1'b0;
            period_start <= 1'b0;
        end else begin
            // Turning points only flip the direction, so the end values repeat once.
            adc_trigger <= up && cnt == period_half - 1'b1;
            period_start <= !up && cnt == 0;
            if (up) begin
                if (cnt == period_half - 1'b1) up <= 1'b0;
                else cnt <= cnt + 1'b1;
            end else if (cnt == 0) begin
                up <= 1'b1;
                da <= clamp(duty_a);
                db <= clamp(duty_b);
                dc <= clamp(duty_c);
            end else cnt <= cnt - 1'b1;
            if (brake) begin
                hi <= 3'b000;
                lo <= 3'b111;
            end else begin
                hi <= {{1'b0, cnt} >= th_c + DEADTIME, {1'b0, cnt} >= th_b + DEADTIME,
                       {1'b0, cnt} >= th_a + DEADTIME};
                lo <= {{1'b0, cnt} < th_c, {1'b0, cnt} < th_b, {1'b0, cnt} < th_a};
            end
        end
    end
endmodule
