// Position / velocity PID of one axis, once per control tick, on ONE 18x18 multiplier used three
// times (kp * e, kd * ve, ki * e): 10 axes then need 10 of the LFE5U-12F's 28 multipliers, plus 10
// for commutation. Gains are unsigned Q8.8 (FRAC = 8); the integral is kept in output units x 2^FRAC
// and narrowly clamped (thesis 6.3: weak P, narrowly clamped I, so a person can backdrive the arm).
//   position mode: u = (kp e + kd (vel_sp - vel) + I) / 2^FRAC + ff,  I += ki e
//   velocity mode: u = (kd (vel_sp - vel) + I) / 2^FRAC + ff,         I += ki (vel_sp - vel)
// hold_i clears the integral (brake, mode change). u saturates at +-out_max.
module pid_axis #(
    parameter FRAC = 8
) (
    input wire clk,
    input wire rst,
    input wire start,
    input wire velocity_mode,
    input wire hold_i,
    input wire signed [31:0] pos_sp,  // encoder counts (multi-turn)
    input wire signed [31:0] pos,
    input wire signed [15:0] vel_sp,  // counts per control tick
    input wire signed [15:0] vel,
    input wire signed [15:0] ff,  // feed-forward, output units (PWM counts)
    input wire [15:0] kp,
    input wire [15:0] ki,
    input wire [15:0] kd,
    input wire [15:0] i_clamp,  // output units
    input wire [15:0] out_max,
    output reg signed [15:0] u,
    output reg done
);
    function signed [17:0] sat18(input signed [32:0] x);
        sat18 = (x > 33'sd131071) ? 18'sd131071 : (x < -33'sd131072) ? -18'sd131072 : x[17:0];
    endfunction

    reg [3:0] state;
    reg signed [17:0] e, ve, mul_a, mul_b;
    reg signed [35:0] prod;
    reg signed [39:0] acc;
    reg signed [31:0] integ;
    reg signed [39:0] isum, with_ff;  // registered: the long adders and the clamps get a clock each
    wire signed [31:0] ilim = $signed({8'd0, i_clamp, {FRAC{1'b0}}});  // i_clamp << FRAC
    wire signed [39:0] total = (acc + integ) >>> FRAC;
    reg signed [39:0] umax, umin;  // registered limits: the configuration is static, keep it off paths

    always @(posedge clk) begin
        prod <= mul_a * mul_b;  // every clock: maps onto one MULT18X18D
        umax <= $signed({24'd0, out_max});
        umin <= -$signed({24'd0, out_max});
        if (rst) begin
            state <= 0;
            done <= 1'b0;
            u <= 0;
            integ <= 0;
            mul_a <= 0;
            mul_b <= 0;
        end else begin
            done <= 1'b0;
            if (hold_i) integ <= 0;
            case (state)
                4'd0: if (start) begin
                    e <= velocity_mode ? 18'sd0 : sat18(pos_sp - pos);
                    ve <= sat18(vel_sp - vel);
                    state <= 4'd1;
                end
                4'd1: begin mul_a <= e; mul_b <= {2'b0, kp}; state <= 4'd2; end
                4'd2: begin mul_a <= ve; mul_b <= {2'b0, kd}; state <= 4'd3; end
                4'd3: begin  // prod = kp e
                    acc <= prod;
                    mul_a <= velocity_mode ? ve : e;
                    mul_b <= {2'b0, ki};
                    state <= 4'd4;
                end
                4'd4: begin acc <= acc + prod; state <= 4'd5; end  // prod = kd ve
                4'd5: begin isum <= integ + prod; state <= 4'd6; end  // prod = ki x
                4'd6: begin
                    if (!hold_i)
                        integ <= (isum > ilim) ? ilim : (isum < -ilim) ? -ilim : isum[31:0];
                    state <= 4'd7;
                end
                4'd7: begin with_ff <= total + ff; state <= 4'd8; end
                default: begin
                    u <= (with_ff > umax) ? umax[15:0] : (with_ff < umin) ? umin[15:0] : with_ff[15:0];
                    done <= 1'b1;
                    state <= 4'd0;
                end
            endcase
        end
    end
endmodule
